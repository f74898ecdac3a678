"""Checkpoint folders appear whole or not at all; the newest committed one is what resume reads,
after its files are checked against the manifest written with it."""

import json
import os

import pytest

from infinirl.config import ConfigError
from infinirl.runners.checkpoints import ABSENT, Checkpoints, config_changes, verify_checkpoint


def _commit(folders: Checkpoints, index: int, payload: str = "") -> str:
    tmp = folders.begin(index)
    os.makedirs(os.path.join(tmp, "actor"))
    with open(os.path.join(tmp, "actor", "weights.bin"), "w") as handle:
        handle.write(payload or str(index))
    return folders.commit(tmp, index, {"iteration": index})


def test_commit_latest_prune_and_half_written_folders_are_ignored(tmp_path):
    folders = Checkpoints(str(tmp_path))
    assert folders.latest() is None
    for index in (2, 4, 6):
        final = _commit(folders, index)
        assert final.endswith("iter_%06d" % index) and not os.path.exists(final + ".tmp")
    crashed = folders.begin(8)  # a save that died before its commit
    open(os.path.join(crashed, "weights.bin"), "w").write("partial")
    path, state = folders.latest()
    assert state == {"iteration": 6} and open(os.path.join(path, "actor", "weights.bin")).read() == "6"
    folders.prune(2)
    assert folders.completed() == [(4, "iter_000004"), (6, "iter_000006")]
    assert os.path.isdir(crashed)  # left for the next begin(8) to clear, never read as a checkpoint
    assert os.listdir(folders.begin(8)) == []  # a new save starts from an empty folder


def test_keep_prunes_on_commit(tmp_path):
    folders = Checkpoints(str(tmp_path), keep=2)
    for index in (1, 2, 3):
        _commit(folders, index)
    assert [name for _, name in folders.completed()] == ["iter_000002", "iter_000003"]


def test_legacy_step_folders_resume_and_sort_by_number(tmp_path):
    root = tmp_path / "checkpoints"
    (root / "step_000010").mkdir(parents=True)
    (root / "step_000010" / "runner_state.json").write_text(json.dumps({"step": 10}))
    folders = Checkpoints(str(tmp_path))
    assert folders.latest()[1] == {"step": 10}
    _commit(folders, 9)
    assert [name for _, name in folders.completed()] == ["iter_000009", "step_000010"]


def test_a_truncated_file_is_named_with_the_fix(tmp_path):
    folders = Checkpoints(str(tmp_path))
    _commit(folders, 1)
    final = _commit(folders, 2, payload="x" * 100)
    weights = os.path.join(final, "actor", "weights.bin")
    os.truncate(weights, 10)
    with pytest.raises(ConfigError, match=r"checkpoint file .*actor/weights.bin is truncated or altered \(10 bytes, "
                                          r"written with 100\); start over with resume=false, or delete .*iter_000002"):
        folders.latest()
    os.remove(weights)
    with pytest.raises(ConfigError, match=r"weights.bin is missing"):
        folders.latest()


def test_a_corrupt_driver_state_is_named(tmp_path):
    final = _commit(Checkpoints(str(tmp_path)), 1)
    with open(os.path.join(final, "runner_state.json"), "w") as handle:
        handle.write("{not json")
    with pytest.raises(ConfigError, match=r"runner_state.json is not valid JSON"):
        Checkpoints(str(tmp_path)).latest()


def test_verify_checkpoint_checks_one_folder_as_resume_does_with_the_callers_fix(tmp_path):
    """`infinirl eval` checks the checkpoint it loads the same way, naming its own way out."""
    folders = Checkpoints(str(tmp_path))
    final = _commit(folders, 3, payload="x" * 50)
    assert verify_checkpoint(final) == {"iteration": 3}
    os.truncate(os.path.join(final, "actor", "weights.bin"), 5)
    with pytest.raises(ConfigError, match=r"weights.bin is truncated or altered \(5 bytes, written with 50\); "
                                          r"pick another$"):
        verify_checkpoint(final, fix="pick another")
    with open(os.path.join(final, "manifest.json"), "w") as handle:
        handle.write("[1, 2]")
    with pytest.raises(ConfigError, match=r"manifest.json does not hold a mapping; start over with resume=false"):
        verify_checkpoint(final)


def test_config_changes_lists_every_changed_leaf():
    old = {"actor": {"lr": 1e-3, "betas": [0.9, 0.99]}, "iterations": 10, "gone": 1}
    new = {"actor": {"lr": 3e-4, "betas": [0.9, 0.99]}, "iterations": 20, "added": {"x": 1}}
    assert config_changes(old, new) == {"actor.lr": (1e-3, 3e-4), "iterations": (10, 20), "gone": (1, ABSENT),
                                        "added": (ABSENT, {"x": 1})}
    assert config_changes({"a": None}, {}) == {"a": (None, ABSENT)}  # a null value is not a missing key
    assert repr(ABSENT) == str(ABSENT) == "<absent>"


def test_placement_keys_naming_several_components_expand_and_a_repeat_is_refused():
    from infinirl.runners.run_config import expand_placement

    assert expand_placement({"actor,rollout": 1, "reward": "0"}) == {"actor": "1", "rollout": "1", "reward": "0"}
    with pytest.raises(ConfigError, match="placement gives 'actor' twice"):
        expand_placement({"actor": "0", "actor, rollout": "0"})


def test_a_commit_makes_the_new_checkpoint_durable_before_pruning_the_old_ones(tmp_path, monkeypatch):
    """After a power loss the newest checkpoint must hold its bytes and the older ones must not be
    gone first: every file and folder of the new one is fsynced before its rename, the checkpoints
    folder (holding the rename) after it, and only then are older checkpoints deleted."""
    import shutil

    folders = Checkpoints(str(tmp_path), keep=1)
    _commit(folders, 1)
    events = []
    real_fsync, real_replace, real_rmtree = os.fsync, os.replace, shutil.rmtree

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src, dst, **kwargs):
        events.append(("rename", os.fspath(src), os.fspath(dst)))
        real_replace(src, dst, **kwargs)

    def rmtree(path, *args, **kwargs):
        events.append(("delete", os.fspath(path)))
        real_rmtree(path, *args, **kwargs)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(shutil, "rmtree", rmtree)
    tmp = folders.begin(2)
    events.clear()
    os.makedirs(os.path.join(tmp, "actor"))
    with open(os.path.join(tmp, "actor", "weights.bin"), "w") as handle:
        handle.write("2")
    final = folders.commit(tmp, 2, {"iteration": 2})
    moved = events.index(("rename", tmp, final))
    synced_before = {path for kind, path, *_ in events[:moved] if kind == "fsync"}
    inside = {os.path.join(tmp, name) for name in ("actor/weights.bin", "runner_state.json", "manifest.json", "actor")}
    assert inside | {tmp} <= synced_before, events
    root_synced = events.index(("fsync", folders.root), moved)
    pruned = events.index(("delete", folders.path_of(1)))
    assert moved < root_synced < pruned, events
    assert folders.completed() == [(2, "iter_000002")]
