"""The replay buffer: ring wrap-around, seeded sampling, and save/load that continues exactly."""

import os

import numpy as np
import pytest

from infinirl.components.replay_buffer import ReplayBuffer

FIELDS = {"obs": ((3,), "float32"), "action": ((2,), "float32"), "reward": ((), "float32"),
          "done": ((), "bool"), "step": ((), "int64")}


def rows(start: int, n: int) -> dict:
    ids = np.arange(start, start + n)
    return {"obs": np.stack([ids, ids + 0.5, -ids], axis=1).astype(np.float32),
            "action": np.stack([ids * 0.1, -ids * 0.1], axis=1).astype(np.float32),
            "reward": ids.astype(np.float32), "done": ids % 3 == 0, "step": ids}


def test_add_wraps_around_and_keeps_the_newest_rows():
    buffer = ReplayBuffer(5, FIELDS)
    assert len(buffer) == 0 and not buffer.full
    buffer.add(rows(0, 3))
    assert len(buffer) == 3 and buffer.rows()["step"].tolist() == [0, 1, 2]
    buffer.add(rows(3, 4))  # 7 rows into 5: the write crosses the end of the storage
    assert buffer.full and len(buffer) == 5 and buffer.added == 7
    kept = buffer.rows()
    assert kept["step"].tolist() == [2, 3, 4, 5, 6]  # oldest first
    np.testing.assert_array_equal(kept["obs"], rows(2, 5)["obs"])
    np.testing.assert_array_equal(kept["done"], rows(2, 5)["done"])
    buffer.add(rows(7, 12))  # a batch larger than the capacity: only its newest 5 rows stay
    assert buffer.rows()["step"].tolist() == [14, 15, 16, 17, 18] and buffer.added == 19
    assert buffer.add(rows(0, 0)) == 0  # empty batches are fine


def test_add_checks_fields_and_shapes():
    buffer = ReplayBuffer(4, FIELDS)
    bad = rows(0, 2)
    del bad["done"]
    with pytest.raises(ValueError, match=r"missing \['done'\]"):
        buffer.add(bad)
    bad = rows(0, 2)
    bad["obs"] = np.zeros((2, 4), np.float32)
    with pytest.raises(ValueError, match=r"'obs': expected rows of shape \(3,\)"):
        buffer.add(bad)
    bad = rows(0, 2)
    bad["reward"] = np.zeros(3, np.float32)
    with pytest.raises(ValueError, match="'reward'"):
        buffer.add(bad)
    with pytest.raises(ValueError, match="empty"):
        buffer.sample(2)


def test_sampling_is_uniform_over_filled_rows_and_seeded():
    a, b, c = ReplayBuffer(100, FIELDS, seed=7), ReplayBuffer(100, FIELDS, seed=7), ReplayBuffer(100, FIELDS, seed=8)
    for buffer in (a, b, c):
        buffer.add(rows(0, 40))
    first = a.sample(64)
    np.testing.assert_array_equal(first["step"], b.sample(64)["step"])  # same seed, same batches
    assert not np.array_equal(first["step"], c.sample(64)["step"])
    assert first["step"].min() >= 0 and first["step"].max() < 40  # only filled rows
    np.testing.assert_array_equal(first["obs"], rows(0, 40)["obs"][first["step"]])  # rows stay aligned
    counts = np.bincount(a.sample_indices(40_000), minlength=40)
    assert counts.min() > 800 and counts.max() < 1200  # ~1000 each: uniform
    first["step"][:] = -5  # samples are copies: writing to them leaves the buffer alone
    assert a.rows()["step"].tolist() == list(range(40))


def test_save_load_continues_exactly(tmp_path):
    original = ReplayBuffer(6, FIELDS, seed=3)
    original.add(rows(0, 9))  # wrapped
    original.sample(5)  # advance the generator
    path = original.save(str(tmp_path / "buffer.npz"))
    assert sorted(os.listdir(tmp_path)) == ["buffer.npz"]  # no temporary file left behind

    restored = ReplayBuffer(6, FIELDS, seed=999)  # the seed is overwritten by the saved generator state
    restored.load(path)
    rebuilt = ReplayBuffer.from_file(path)
    assert restored.digest() == original.digest() == rebuilt.digest()
    for _ in range(3):  # same samples, same writes, same samples again
        expected = original.sample(8)
        for other in (restored, rebuilt):
            got = other.sample(8)
            for key in FIELDS:
                np.testing.assert_array_equal(got[key], expected[key])
        for buffer in (original, restored, rebuilt):
            buffer.add(rows(100, 4))
    assert restored.digest() == original.digest()

    partial = ReplayBuffer(50, FIELDS, seed=1)  # not yet full: only the filled rows are written
    partial.add(rows(0, 7))
    partial.save(str(tmp_path / "partial.npz"))
    assert ReplayBuffer.from_file(str(tmp_path / "partial.npz")).digest() == partial.digest()


def test_save_is_atomic_and_load_checks_the_config(tmp_path, monkeypatch):
    buffer = ReplayBuffer(4, FIELDS, seed=0)
    buffer.add(rows(0, 4))
    path = buffer.save(str(tmp_path / "buffer.npz"))
    before = open(path, "rb").read()

    def crash(*args, **kwargs):
        raise OSError("disk full")

    buffer.add(rows(10, 2))
    monkeypatch.setattr(np, "savez", crash)
    with pytest.raises(OSError, match="disk full"):
        buffer.save(path)
    monkeypatch.undo()
    assert open(path, "rb").read() == before  # the previous file is intact
    assert sorted(os.listdir(tmp_path)) == ["buffer.npz"]  # and the temporary file is gone

    with pytest.raises(ValueError, match="capacity 4 .* this buffer has capacity 8"):
        ReplayBuffer(8, FIELDS).load(path)
