"""An episode appended with a source id is stored once: a repeated append of that source id writes
nothing, also after a reopen; a source line whose episode never committed (the writer died between
the two) is dropped on reopen, so that source is stored when it comes again."""

import errno
import os

import pytest

from infinirl.realworld.replay import ReplayStore, StoreOptions
from infinirl.realworld.replay.sources import SOURCES_NAME
from tests.unit.realworld.replay_fixtures import SPEC, make_episode

OPTIONS = StoreOptions(segment_bytes=10**6, durable=False)


def test_a_source_id_is_stored_once_also_after_a_reopen(tmp_path):
    with ReplayStore(str(tmp_path), SPEC, options=OPTIONS) as store:
        assert [store.append(make_episode(i), source_id=f"edge-0-a-{i}") for i in range(3)] == [0, 1, 2]
        assert store.append(make_episode(7), source_id="edge-0-a-1") == 1  # a resend: not stored again
        assert store.append(make_episode(3)) == 3  # no source id: always appended
        assert store.num_episodes == 4 and store.episode_of_source("edge-0-a-9") is None
    with ReplayStore(str(tmp_path), options=OPTIONS) as store:
        assert store.append(make_episode(8), source_id="edge-0-a-2") == 2
        assert store.num_episodes == 4
        assert store.sources.sources() == {"edge-0-a-0": 0, "edge-0-a-1": 1, "edge-0-a-2": 2}
    with ReplayStore(str(tmp_path), writable=False) as reader:
        assert reader.episode_of_source("edge-0-a-1") == 1


def test_a_source_whose_episode_never_committed_is_stored_when_it_comes_again(tmp_path):
    with ReplayStore(str(tmp_path), SPEC, options=OPTIONS) as store:
        store.append(make_episode(0), source_id="s-0")
        store.sources.intend("s-1", 1)  # the writer died here: the line is written, the episode is not
    with open(tmp_path / SOURCES_NAME, "a") as handle:
        handle.write("2 s-")  # and a torn line
    with ReplayStore(str(tmp_path), writable=False) as reader:
        assert reader.episode_of_source("s-1") is None and reader.episode_of_source("s-0") == 0
    with ReplayStore(str(tmp_path), options=OPTIONS) as store:
        assert store.episode_of_source("s-1") is None
        assert (tmp_path / SOURCES_NAME).read_text() == "0 s-0\n"  # reopening dropped both lines
        assert store.append(make_episode(1), source_id="s-1") == 1
        assert store.episode(1)["episode"][0] == 1


def test_a_failed_append_cancels_its_source_line(tmp_path):
    with ReplayStore(str(tmp_path), SPEC, options=OPTIONS) as store:
        store.sources.intend("s-0", 0)
        store.sources.forget("s-0")  # what append does when the segment write fails
        store.append(make_episode(0))  # episode 0 commits without a source id
        with pytest.raises(ValueError, match="no whitespace"):
            store.append(make_episode(1), source_id="a b")
    with ReplayStore(str(tmp_path), options=OPTIONS) as store:
        assert store.episode_of_source("s-0") is None and store.num_episodes == 1


def test_a_durable_store_makes_the_name_of_a_new_sources_log_durable(tmp_path, monkeypatch):
    from infinirl.realworld.replay import sources as sources_module

    synced = []
    monkeypatch.setattr(sources_module, "fsync_directory", lambda folder: synced.append(str(folder)))
    ReplayStore(str(tmp_path), SPEC, options=StoreOptions(durable=True)).close()
    assert synced == [str(tmp_path)]  # the folder holds the new file's name
    ReplayStore(str(tmp_path), options=StoreOptions(durable=True)).close()  # the log exists: nothing new
    ReplayStore(str(tmp_path / "other"), SPEC, options=OPTIONS).close()  # not durable
    assert synced == [str(tmp_path)]


@pytest.mark.parametrize("failing", ["write", "fsync"])
def test_a_source_line_whose_write_fails_leaves_nothing_behind(tmp_path, monkeypatch, failing):
    """A part of a line would run into the next one; a whole line whose fsync failed would name
    ``s-1`` as the source of the episode the next append (without a source id) commits."""
    options = StoreOptions(segment_bytes=10**6, durable=True)
    with ReplayStore(str(tmp_path), SPEC, options=options) as store:
        store.append(make_episode(0), source_id="s-0")
        real = getattr(os, failing)

        def full_disk(fd, *args):
            if failing == "write" and len(args[0]) > 2:
                real(fd, args[0][:2])  # the first bytes land, then the disk is full
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        with monkeypatch.context() as patch:
            patch.setattr(os, failing, full_disk)
            with pytest.raises(OSError, match="No space"):
                store.append(make_episode(1), source_id="s-1")
        assert (tmp_path / SOURCES_NAME).read_text() == "0 s-0\n"
        assert store.append(make_episode(1)) == 1
        assert store.append(make_episode(2), source_id="s-2") == 2
    with ReplayStore(str(tmp_path), options=options) as store:
        assert store.sources.sources() == {"s-0": 0, "s-2": 2}
