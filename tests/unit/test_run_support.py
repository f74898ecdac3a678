"""Checkpoint folders appear whole or not at all; the newest committed one is what resume reads."""

import os

from infinirl.runners.run_support import CheckpointFolders


def test_commit_latest_prune_and_half_written_folders_are_ignored(tmp_path):
    folders = CheckpointFolders(str(tmp_path), "iter_")
    assert folders.latest() is None
    for index in (2, 4, 6):
        tmp = folders.begin(index)
        open(os.path.join(tmp, "weights.bin"), "w").write(str(index))
        final = folders.commit(tmp, index, {"iteration": index})
        assert final.endswith("iter_%06d" % index) and not os.path.exists(tmp)
    crashed = folders.begin(8)  # a save that died before its commit
    open(os.path.join(crashed, "weights.bin"), "w").write("partial")
    path, state = folders.latest()
    assert state == {"iteration": 6} and open(os.path.join(path, "weights.bin")).read() == "6"
    folders.prune(2)
    assert folders.completed() == ["iter_000004", "iter_000006"]
    assert os.path.isdir(crashed)  # left for the next begin(8) to clear, never read as a checkpoint
    assert os.listdir(folders.begin(8)) == []  # a new save starts from an empty folder
