"""Atomic writes leave the old file or the new one, never a torn one; RNG state round-trips."""

import os
import random

import numpy as np
import pytest
import torch

from infinirl.utils import (
    atomic_open,
    capture_rng_state,
    replace_directory,
    restore_rng_state,
    seed_everything,
    torch_save_atomic,
    write_json_atomic,
)


def test_a_failed_write_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "state.json"
    write_json_atomic(target, {"version": 1})
    with pytest.raises(RuntimeError):
        with atomic_open(target, "w") as handle:
            handle.write('{"version": 2')  # half written, then the writer dies
            raise RuntimeError("disk full")
    assert target.read_text() == '{\n  "version": 1\n}\n'
    assert os.listdir(tmp_path) == ["state.json"]


def test_a_durable_write_fsyncs_the_file_and_then_its_folder(tmp_path, monkeypatch):
    """The rename is an entry of the folder: only an fsync of the folder after it makes the new file
    survive a power loss; a plain write fsyncs nothing."""
    import stat

    import infinirl.utils.atomic as atomic

    synced, real_fsync = [], os.fsync

    def recording(fd):
        synced.append("folder" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", recording)
    with atomic_open(tmp_path / "plain.bin", "wb") as handle:
        handle.write(b"x")
    assert synced == []
    with atomic_open(tmp_path / "kept.bin", "wb", durable=True) as handle:
        handle.write(b"y")
    assert synced == ["file", "folder"] and (tmp_path / "kept.bin").read_bytes() == b"y"


def test_torch_save_atomic_round_trips_and_creates_the_folder(tmp_path):
    target = tmp_path / "deep" / "model.pt"
    torch_save_atomic({"w": torch.arange(3)}, target, durable=True)
    assert torch.equal(torch.load(target)["w"], torch.arange(3))


def test_replace_directory_swaps_in_the_new_folder(tmp_path):
    (tmp_path / "ckpt").mkdir()
    (tmp_path / "ckpt" / "old").write_text("old")
    (tmp_path / "new").mkdir()
    (tmp_path / "new" / "fresh").write_text("fresh")
    replace_directory(tmp_path / "new", tmp_path / "ckpt")
    assert sorted(os.listdir(tmp_path)) == ["ckpt"]
    assert os.listdir(tmp_path / "ckpt") == ["fresh"]


def test_atomic_open_refuses_append_mode(tmp_path):
    with pytest.raises(ValueError, match="mode must be 'w' or 'wb'"):
        with atomic_open(tmp_path / "x", "a"):
            pass


def test_restoring_rng_state_replays_every_generator():
    seed_everything(7)
    state = capture_rng_state()
    first = (random.random(), np.random.rand(), torch.rand(1).item())
    restore_rng_state(state)
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == first


def test_atomic_path_gives_writers_a_file_name_and_cleans_up(tmp_path):
    from infinirl.utils import atomic_path

    with atomic_path(tmp_path / "video.mp4", suffix=".tmp.mp4") as tmp:
        assert tmp.endswith(".tmp.mp4") and str(tmp_path) in tmp
        with open(tmp, "w") as handle:
            handle.write("frames")
    assert (tmp_path / "video.mp4").read_text() == "frames"
    with pytest.raises(OSError):
        with atomic_path(tmp_path / "other.mp4") as tmp:
            raise OSError("encoder failed")
    assert sorted(os.listdir(tmp_path)) == ["video.mp4"]
