"""Crash consistency (a writer process killed with SIGKILL mid-append), torn tails, damaged bytes
in committed data, and a reader process beside the writer."""

import errno
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from infinirl.realworld.replay import ReplayCorruptionError, ReplayStore, StoreOptions
from infinirl.realworld.replay.segment import LOG_NAME
from tests.unit.realworld.replay_fixtures import SPEC, check_batch, make_episode, source_of

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
SEGMENT_BYTES, MAX_BYTES = 3000, 15000


def start_writer(path, limit=None):
    args = [sys.executable, "-m", "tests.unit.realworld.replay_fixtures", str(path), str(SEGMENT_BYTES), str(MAX_BYTES)]
    return subprocess.Popen(args + ([str(limit)] if limit else []), cwd=REPO, stdout=subprocess.PIPE, text=True)


def read_line(proc, deadline_s=60.0):
    start = time.monotonic()
    line = proc.stdout.readline()
    assert line, f"the writer process exited early (rc {proc.poll()})"
    assert time.monotonic() - start < deadline_s
    return line.split()


def check_store(store):
    first = int(store.segments[min(store.segments)].episode_ids[0])
    for i in range(first, store.next_episode_id):
        got = store.episode(i)
        for name, want in make_episode(i).items():
            np.testing.assert_array_equal(got[name], want, err_msg=f"episode {i} {name}")
    for _ in range(5):
        check_batch(store.sample(32))


def test_kill_9_during_appends_loses_at_most_the_episode_in_flight(tmp_path):
    rng = random.Random(2024)
    path = tmp_path / "store"
    last = -1
    for _ in range(6):
        proc = start_writer(path)
        assert read_line(proc) == ["opened", str(last + 1)]  # continues right after the last commit
        for _ in range(rng.randint(2, 30)):
            kind, episode = read_line(proc)
            last = int(episode)
        time.sleep(rng.uniform(0.0, 0.01))  # lands in a write, an fsync, a seal or an eviction
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        for line in proc.stdout:  # commits it reported before it died
            last = int(line.split()[1])
        proc.stdout.close()
        with ReplayStore(str(path), writable=False) as reader:  # before any recovery: committed episodes only
            assert reader.next_episode_id in (last + 1, last + 2)
            check_store(reader)
        with ReplayStore(str(path), options=StoreOptions(segment_bytes=SEGMENT_BYTES, max_bytes=MAX_BYTES)) as store:
            assert store.next_episode_id in (last + 1, last + 2)  # the one in flight may have committed
            # every committed episode's source id is known, the one in flight's only if it committed
            assert store.sources.sources() == {source_of(i): i for i in range(store.next_episode_id)}
            for segment in store.segments.values():  # the rows of an uncommitted episode are cut off
                for name in segment.names:
                    assert os.path.getsize(segment.file(name)) == segment.rows(name) * SPEC.row_bytes(name), name
            store.append(make_episode(store.next_episode_id), source_id=source_of(store.next_episode_id))
            check_store(store)
            store.verify()
            last = store.next_episode_id - 1
    assert last > 20


def active_segment(path):
    segments = sorted(os.listdir(path / "segments"))
    return path / "segments" / segments[-1]


def test_a_torn_tail_is_cut_off_on_reopen_and_appends_continue(tmp_path):
    options = StoreOptions(segment_bytes=10**6, durable=False)
    with ReplayStore(str(tmp_path), SPEC, options=options) as store:
        for i in range(4):
            store.append(make_episode(i))
    segment = active_segment(tmp_path)
    sizes = {name: os.path.getsize(segment / name) for name in os.listdir(segment)}
    with open(segment / "pixels.bin", "ab") as handle:  # an episode whose data and record were half written
        handle.write(b"\x07" * 500)
    with open(segment / LOG_NAME, "ab") as handle:
        handle.write(b"IRE1\x05\x00")
    with ReplayStore(str(tmp_path), writable=False) as reader:
        assert reader.next_episode_id == 4
        check_store(reader)
    with ReplayStore(str(tmp_path), options=options) as store:
        assert store.next_episode_id == 4
        assert {name: os.path.getsize(segment / name) for name in sizes} == sizes  # torn bytes cut off
        store.append(make_episode(4))
        check_store(store)
    with ReplayStore(str(tmp_path), options=options) as store:
        assert store.next_episode_id == 5
        check_store(store)


def build(path, **options):
    options = StoreOptions(segment_bytes=SEGMENT_BYTES, durable=False, **options)
    with ReplayStore(str(path), SPEC, options=options) as store:
        for i in range(20):
            store.append(make_episode(i))
        while store.segments[max(store.segments)].sealed:  # end with an open segment
            store.append(make_episode(store.next_episode_id))
        assert len(store.segments) > 3


def flip_byte(file, offset):
    with open(file, "r+b") as handle:
        handle.seek(offset)
        byte = handle.read(1)
        handle.seek(offset)
        handle.write(bytes([byte[0] ^ 0x10]))


def one_line_naming(info, file):
    message = str(info.value)
    assert str(file) in message and "\n" not in message, message


def test_a_damaged_byte_in_a_sealed_segment_is_named_before_its_rows_are_used(tmp_path):
    build(tmp_path)
    damaged = tmp_path / "segments" / "00000000" / "pixels.bin"
    flip_byte(damaged, 150)  # inside episode 0's second observation
    with pytest.raises(ReplayCorruptionError, match="episode 0 .* fails its crc32") as info:
        ReplayStore(str(tmp_path), writable=False, options=StoreOptions(cache_bytes=10**6))  # loading it into the cache
    one_line_naming(info, damaged)
    with ReplayStore(str(tmp_path), writable=False, options=StoreOptions(cache_bytes=0)) as store:
        check_batch(store.gather(np.arange(8, 16)))  # episodes 1 and 2 are intact and readable
        with pytest.raises(ReplayCorruptionError, match="fails its crc32") as info:
            store.gather(np.arange(0, 2))  # a read through the memory map
        one_line_naming(info, damaged)
        with pytest.raises(ReplayCorruptionError) as info:
            store.verify()
        one_line_naming(info, damaged)


@pytest.mark.parametrize("segment", ["00000000", "last"])
def test_a_damaged_commit_log_is_named_on_open(tmp_path, segment):
    build(tmp_path)
    folder = tmp_path / "segments" / segment if segment != "last" else active_segment(tmp_path)
    assert (folder / "sealed.json").exists() == (segment != "last")
    flip_byte(folder / LOG_NAME, 10)  # a full record (not a torn tail): damage, never cut off silently
    for writable in (False, True):
        with pytest.raises(ReplayCorruptionError) as info:
            ReplayStore(str(tmp_path), writable=writable)
        one_line_naming(info, folder / LOG_NAME)


def test_a_truncated_field_file_is_named_on_open(tmp_path):
    build(tmp_path)
    damaged = tmp_path / "segments" / "00000001" / "action.bin"
    os.truncate(damaged, os.path.getsize(damaged) - 8)
    with pytest.raises(ReplayCorruptionError, match="bytes, the commit log says") as info:
        ReplayStore(str(tmp_path), writable=False)
    one_line_naming(info, damaged)


def test_a_reader_process_sees_committed_episodes_while_the_writer_appends(tmp_path):
    path = tmp_path / "store"
    proc = start_writer(path, limit=150)
    try:
        assert read_line(proc)[0] == "opened"
        read_line(proc)
        with pytest.raises(RuntimeError, match=rf"open for writing by process {proc.pid}; one writer"):
            ReplayStore(str(path), SPEC)
        reader = ReplayStore(str(path), writable=False, options=StoreOptions(cache_bytes=2 * SEGMENT_BYTES))
        seen = [reader.next_episode_id]
        while proc.poll() is None or seen[-1] < 150:
            reader.refresh()
            seen.append(reader.next_episode_id)
            check_batch(reader.sample(32))  # never a partial episode, even the one being written
            if proc.poll() is not None and reader.next_episode_id == seen[-2]:
                break
        assert seen == sorted(seen) and len(set(seen)) > 2  # it saw the store grow
        assert reader.next_episode_id == 150 and proc.wait() == 0
        assert min(reader.segments) > 0  # the writer's evictions reached the reader
        check_store(reader)
        reader.close()
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()


def test_a_segment_sealed_while_a_reader_opens_it_is_taken_as_open_not_as_damaged(tmp_path, monkeypatch):
    """The writer may append and seal between a reader's read of the open segment's log and its look
    for ``sealed.json``: the reader must not compare its shorter read with the seal's sizes."""
    from infinirl.realworld.replay import segment as segment_module

    path = tmp_path / "store"
    writer = ReplayStore(str(path), SPEC, options=StoreOptions(segment_bytes=SEGMENT_BYTES, durable=False))
    for _ in range(2):
        writer.append(make_episode(writer.next_episode_id))
    open_segment = max(writer.segments)
    real_scan, raced = segment_module.scan_records, []

    def scan_then_writer_seals(data, fields, log_path):
        records = real_scan(data, fields, log_path)
        if not raced and log_path.startswith(str(writer.segments[open_segment].path)):
            raced.append(True)
            while max(writer.segments) == open_segment:  # appends until that segment seals
                writer.append(make_episode(writer.next_episode_id))
        return records

    monkeypatch.setattr(segment_module, "scan_records", scan_then_writer_seals)
    reader = ReplayStore(str(path), writable=False)
    assert raced
    reader.refresh()
    assert reader.next_episode_id == writer.next_episode_id
    check_store(reader)
    reader.close()
    writer.close()


def fail_from_call(real, n, partial=False):
    """``real`` (``os.write``, ``os.fdatasync``) failing with ENOSPC from its ``n``-th call on; with
    ``partial`` the ``n``-th write lands half of its bytes first, as on a disk that fills up."""
    calls = [0]

    def call(fd, *args):
        calls[0] += 1
        if calls[0] == n and partial and len(args[0]) > 1:
            return real(fd, args[0][:len(args[0]) // 2])
        if calls[0] >= n:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, *args)

    return call


def check_files_hold_only_committed_bytes(store):
    for segment in store.segments.values():
        for name in segment.names:
            assert os.path.getsize(segment.file(name)) == segment.rows(name) * SPEC.row_bytes(name), name
        assert os.path.getsize(os.path.join(segment.path, LOG_NAME)) == segment.log_bytes


@pytest.mark.parametrize("durable", [False, True])
def test_a_write_or_fsync_that_fails_leaves_no_bytes_that_shift_later_episodes(tmp_path, monkeypatch, durable):
    """A full disk or an I/O error part-way through an append (the process lives on): the next
    appends' rows must start where the commit records say, in this process (which reads its own
    episodes unchecked: no cache here, so through the memory maps) and after a reopen."""
    options = StoreOptions(segment_bytes=SEGMENT_BYTES, durable=durable, cache_bytes=0)
    # write calls per append: the source line, one per field, the commit record
    failures = [("write", n) for n in range(1, len(SPEC.fields) + 3)]
    if durable:  # fdatasync calls: one per field, then the commit record's
        failures += [("fdatasync", n) for n in range(1, len(SPEC.fields) + 2)]
    store = ReplayStore(str(tmp_path), SPEC, options=options)
    for call, n in failures:
        episode_id = store.next_episode_id
        with monkeypatch.context() as patch:
            patch.setattr(os, call, fail_from_call(getattr(os, call), n, partial=call == "write"))
            with pytest.raises(OSError):
                store.append(make_episode(episode_id), source_id=source_of(episode_id))
        assert store.next_episode_id == episode_id and store.episode_of_source(source_of(episode_id)) is None
        check_files_hold_only_committed_bytes(store)
        assert store.append(make_episode(episode_id), source_id=source_of(episode_id)) == episode_id
    assert len(store.segments) > 2  # failures in fresh segments and in ones with episodes
    check_store(store)
    store.close()
    with ReplayStore(str(tmp_path), options=options) as store:
        assert store.next_episode_id == len(failures)
        assert store.sources.sources() == {source_of(i): i for i in range(len(failures))}
        check_store(store)
        store.verify()


def test_bytes_a_failed_append_could_not_cut_off_are_cut_before_the_next_append(tmp_path, monkeypatch):
    options = StoreOptions(segment_bytes=10**6, durable=False, cache_bytes=0)
    store = ReplayStore(str(tmp_path), SPEC, options=options)
    store.append(make_episode(0))

    def broken(fd, size):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    with monkeypatch.context() as patch:
        patch.setattr(os, "ftruncate", broken)
        with monkeypatch.context() as full:
            full.setattr(os, "write", fail_from_call(os.write, 3, partial=True))
            with pytest.raises(OSError, match="No space") as info:
                store.append(make_episode(1))
        assert "the next append tries again" in " ".join(info.value.__notes__)
        segment = store.segments[0]
        sizes = {name: os.path.getsize(segment.file(name)) for name in segment.names}
        assert sizes["pixels"] > segment.rows("pixels") * SPEC.row_bytes("pixels")
        with pytest.raises(OSError, match="Input/output"):  # still not cut: nothing written after them
            store.append(make_episode(1))
        assert {name: os.path.getsize(segment.file(name)) for name in segment.names} == sizes
    assert store.append(make_episode(1)) == 1
    check_files_hold_only_committed_bytes(store)
    check_store(store)
    store.close()
    with ReplayStore(str(tmp_path), options=options) as store:
        assert store.next_episode_id == 2
        check_store(store)


def test_a_failed_seal_leaves_the_segment_open_for_the_next_append(tmp_path, monkeypatch):
    """The episode whose append reached the seal is committed; the next appends go on into the same
    segment (its copy in the cache included) and seal it."""
    from infinirl.realworld.replay import segment as segment_module

    options = StoreOptions(segment_bytes=SEGMENT_BYTES, durable=False)

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    store = ReplayStore(str(tmp_path), SPEC, options=options)
    with monkeypatch.context() as patch:
        patch.setattr(segment_module, "atomic_open", full_disk)
        with pytest.raises(OSError, match="No space"):
            while True:
                store.append(make_episode(store.next_episode_id))
    committed = store.next_episode_id
    assert store.segments[0].num_episodes == committed and not store.segments[0].sealed
    assert not os.path.exists(os.path.join(store.segments[0].path, "sealed.json"))
    store.append(make_episode(committed))
    assert store.segments[0].sealed and store.segments[0].num_episodes == committed + 1
    while len(store.segments) < 3:
        store.append(make_episode(store.next_episode_id))
    check_store(store)  # read from the cache, which holds the segments' rows
    store.close()
    with ReplayStore(str(tmp_path), options=options) as store:
        check_store(store)
        store.verify()
