"""The shared-memory pool of channel items: layout, reuse, bounds, and what a producer's exit leaves."""

import gc
import logging
import os
import pickle
import signal
import subprocess
import sys
import textwrap
from dataclasses import dataclass

import pytest
import torch
from tensordict import TensorDict

from infinirl.runtime import shm_pool, transport
from infinirl.runtime.errors import ChannelError
from infinirl.runtime.shm_pool import FREE, MIN_SEGMENT_BYTES, ShmPool, size_class

MIB = 1 << 20


@dataclass
class Step:
    obs: torch.Tensor
    reward: float


def _segment_states(pool: ShmPool) -> list[int]:
    return [segment.state for segment in pool.segments]


def _memfd_maps() -> list[str]:
    with open("/proc/self/maps") as maps:
        return [line for line in maps if "infinirl-shm" in line]


def _assert_same(sent, got):
    if isinstance(sent, torch.Tensor):
        assert got.dtype == sent.dtype and got.shape == sent.shape and torch.equal(got, sent)
    elif isinstance(sent, TensorDict):
        assert got.batch_size == sent.batch_size and sent.keys() == got.keys()
        for key in sent.keys():
            _assert_same(sent[key], got[key])
    elif isinstance(sent, dict):
        assert sent.keys() == got.keys()
        for key in sent:
            _assert_same(sent[key], got[key])
    elif isinstance(sent, (list, tuple)):
        assert type(sent) is type(got) and len(sent) == len(got)
        for a, b in zip(sent, got):
            _assert_same(a, b)
    elif isinstance(sent, Step):
        assert isinstance(got, Step) and got.reward == sent.reward
        _assert_same(sent.obs, got.obs)
    else:
        assert got == sent


def test_size_class_rounds_up_by_at_most_an_eighth_in_whole_pages():
    previous = 0
    for nbytes in [1, 4096, MIN_SEGMENT_BYTES, MIN_SEGMENT_BYTES + 1, 1000_003, MIB, MIB + 64, 64 * MIB + 64,
                   3 * 10**9]:
        size = size_class(nbytes)
        assert size >= nbytes and size % 4096 == 0 and size >= previous
        if nbytes >= MIN_SEGMENT_BYTES:
            assert size <= nbytes * 1.125 + 4096
        previous = size
    assert size_class(1) == MIN_SEGMENT_BYTES
    assert size_class(MIB + 64) == size_class(MIB + 4000), "items of similar sizes share a class"


def test_every_dtype_and_container_roundtrips_as_writable_views():
    pool = ShmPool(cap_bytes=64 * MIB)
    torch.manual_seed(0)
    base = torch.randn(64, 33)
    payload = {
        "f32": base,
        "bf16": base.to(torch.bfloat16),
        "f16": base.to(torch.float16),
        "f64": base.double().t(),  # not contiguous
        "i64": torch.arange(-5, 1000, dtype=torch.int64),
        "u8": torch.randint(0, 255, (7, 3), dtype=torch.uint8),
        "bool": base > 0,
        "c64": torch.complex(base, -base),
        "fp8": base.to(torch.float8_e4m3fn),
        "scalar": torch.tensor(3.5),
        "empty": torch.zeros(0, 4),
        "nested": [base[::2, 1:5], (base[0], "tag", 7)],
        "td": TensorDict({"ids": torch.arange(12).reshape(4, 3)}, batch_size=[4]),
        "step": Step(obs=base[:3], reward=1.25),
        "plain": {"note": "a python object"},
    }
    item = pool.write(payload)
    got = shm_pool.read(item)
    fp8_sent, fp8_got = payload.pop("fp8"), got.pop("fp8")  # no torch.equal for float8: compare the bytes
    assert fp8_got.dtype == torch.float8_e4m3fn and torch.equal(fp8_sent.view(torch.uint8), fp8_got.view(torch.uint8))
    _assert_same(payload, got)
    got["f32"].add_(1)  # the consumer may modify the item in place
    assert torch.equal(got["f32"], base + 1)


def test_a_segment_is_reused_once_every_view_of_its_item_is_gone():
    pool = ShmPool(cap_bytes=64 * MIB)
    first = pool.write({"x": torch.full((MIB // 4,), 1.0), "y": torch.ones(10)})
    got = shm_pool.read(first)
    kept = got["x"][10:20]  # a view of a view still holds the item
    del got
    gc.collect()
    assert _segment_states(pool) == [1]
    second = pool.write({"x": torch.full((MIB // 4,), 2.0), "y": torch.ones(10)})
    assert second.inode != first.inode and pool.stats["created"] == 2, "a held segment is never reused"
    assert torch.equal(kept, torch.full((10,), 1.0)), "a held item is never overwritten"
    del kept
    assert _segment_states(pool)[0] == FREE
    third = pool.write({"x": torch.full((MIB // 4,), 3.0), "y": torch.ones(10)})
    assert third.inode == first.inode and third.generation == first.generation + 1
    assert pool.stats["created"] == 2
    assert torch.equal(shm_pool.read(third)["x"], torch.full((MIB // 4,), 3.0))


def test_a_free_segment_far_larger_than_the_item_is_not_taken_while_there_is_room():
    pool = ShmPool(cap_bytes=16 * MIB)
    big = pool.write(torch.ones(4 * MIB // 4))
    pool.release(big)
    small = pool.write(torch.ones(MIB // 4))
    assert small.inode != big.inode and small.capacity == size_class(MIB + 64)
    pool.release(small)
    assert pool.write(torch.ones(MIB // 4 + 100)).inode == small.inode, "a close fit is reused"


def test_over_the_cap_an_item_falls_back_and_free_segments_make_room(caplog):
    pool = ShmPool(cap_bytes=4 * MIB + MIB // 2)  # four segments of an item of 1 MiB
    held = [shm_pool.read(pool.write(torch.ones(MIB // 4))) for _ in range(4)]
    with caplog.at_level(logging.WARNING, logger="infinirl.runtime.shm_pool"):
        assert pool.write(torch.ones(MIB // 4)) is None, "no free segment and no room: the object store takes it"
        assert pool.write(torch.ones(8 * MIB // 4)) is None, "larger than the cap"
    assert pool.stats["full"] == 2
    assert len(caplog.records) == 1 and "INFINIRL_SHM_POOL_BYTES" in caplog.records[0].message, "warned once"
    del held[:2]
    larger = pool.write(torch.ones(MIB // 2))  # 2 MiB: both free segments are retired to make room
    assert larger is not None and pool.stats["retired"] == 2 and pool.bytes_held <= pool.cap_bytes
    assert torch.equal(shm_pool.read(larger), torch.ones(MIB // 2))


def test_a_reader_forgets_retired_segments():
    pool = ShmPool(cap_bytes=64 * MIB)
    first = pool.write(torch.ones(MIB // 4))
    shm_pool.read(first)  # mapped here, then released (no view left)
    gc.collect()
    assert (os.getpid(), first.inode) in shm_pool.mapped_segments()
    pool.close()  # retires every free segment
    assert pool.segments == [] and shm_pool.forget_stale_mappings() >= 1
    assert (os.getpid(), first.inode) not in shm_pool.mapped_segments()


def test_release_takes_back_an_unread_item_and_a_stale_descriptor_fails_loudly():
    pool = ShmPool(cap_bytes=64 * MIB)
    refused = pool.write(torch.ones(MIB // 4))
    pool.release(refused)  # its put failed: nobody will read it
    reused = pool.write(torch.zeros(MIB // 4))
    assert reused.inode == refused.inode
    with pytest.raises(ChannelError, match=r"overwritten before it was read \(generation 2, expected 1\)"):
        shm_pool.read(refused)
    assert torch.equal(shm_pool.read(reused), torch.zeros(MIB // 4))


def test_pack_takes_shared_memory_only_when_told_the_consumers_are_on_this_node():
    asked = []

    def consumers_here() -> bool:
        asked.append(True)
        return True

    small = transport.pack(torch.ones(8), shared_memory=consumers_here)
    assert small.path == "inline" and not asked, "a small item never asks"
    envelope = transport.pack({"x": torch.arange(MIB), "meta": "m"}, shared_memory=consumers_here)
    assert envelope.path == "shm" and asked and transport.pinned_node(envelope) == envelope.producer_node
    got = transport.unpack(envelope)
    assert torch.equal(got["x"], torch.arange(MIB)) and got["meta"] == "m"
    assert transport.pinned_node(transport.pack(torch.ones(8))) is None


def test_shared_memory_reaches_only_when_every_consumer_is_on_the_producers_node():
    reaches = transport.shared_memory_reaches
    assert reaches("node-a", ["node-a"])
    assert reaches("node-a", ["node-a", "node-a"])
    assert not reaches("node-a", []), "no consumer known yet: the object store"
    assert not reaches("node-a", ["node-a", "node-b"]), "one consumer elsewhere: the object store"
    assert not reaches("node-a", ["node-b"])


def test_bad_pool_size_setting_is_refused(monkeypatch):
    monkeypatch.setenv(shm_pool.POOL_BYTES_ENV, "1GB")
    with pytest.raises(ValueError, match="INFINIRL_SHM_POOL_BYTES='1GB' is not a number of bytes"):
        shm_pool._cap_from_env()
    monkeypatch.setenv(shm_pool.POOL_BYTES_ENV, "0")
    assert shm_pool._cap_from_env() == 0


_PRODUCER = textwrap.dedent("""
    import pickle, sys, torch
    from infinirl.runtime.shm_pool import ShmPool
    pool = ShmPool(cap_bytes=1 << 26)
    items = [pool.write({"x": torch.full((1 << 18,), float(i))}) for i in range(2)]
    sys.stdout.write(pickle.dumps(items).hex() + "\\n")
    sys.stdout.flush()
    sys.stdin.read()  # lives until killed
""")


def test_a_killed_producer_leaves_nothing_behind():
    """Segments have no name in /dev/shm: a producer killed outright leaves no file; what a reader
    mapped stays readable; what it had not mapped fails with the cause; its memory goes with the
    reader's last view."""
    before = set(os.listdir("/dev/shm"))
    child = subprocess.Popen([sys.executable, "-c", _PRODUCER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        mapped, unmapped = pickle.loads(bytes.fromhex(child.stdout.readline().decode()))
        got = shm_pool.read(mapped)
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=30)
    assert torch.equal(got["x"], torch.full((1 << 18,), 0.0)), "a mapped item outlives its producer"
    with pytest.raises(ChannelError, match=f"pid {child.pid} cannot be read: that process exited"):
        shm_pool.read(unmapped)
    assert (child.pid, mapped.inode) not in shm_pool.mapped_segments(), "mapping a new segment forgot the dead"
    assert [line for line in _memfd_maps() if line.split()[4] == str(mapped.inode)], "the view still maps it"
    del got
    gc.collect()
    assert not [line for line in _memfd_maps() if line.split()[4] == str(mapped.inode)], "its memory is gone"
    assert set(os.listdir("/dev/shm")) <= before
