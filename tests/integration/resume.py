"""Exact-resume checks without a second run of the first half: a finished run is copied as if its
driver had been killed right after an earlier checkpoint, and resumed from there."""

from __future__ import annotations

import shutil
from pathlib import Path

from infinirl.runners.checkpoints import Checkpoints


def killed_after_checkpoint(finished: Path, copy: Path, iteration: int) -> None:
    """``copy``: the run in ``finished`` as it stood when a driver killed after writing the
    checkpoint of ``iteration`` left it. The later checkpoints are gone; the metrics rows logged
    after that checkpoint are still there (resume must drop them)."""
    shutil.copytree(finished, copy, ignore=shutil.ignore_patterns("summary.json", "curves.png", "eval.mp4"))
    checkpoints = Checkpoints(str(copy))
    kept = [index for index, name in checkpoints.completed() if index <= iteration]
    assert kept and kept[-1] == iteration, f"{finished} has no checkpoint of iteration {iteration}"
    for index, name in checkpoints.completed():
        if index > iteration:
            shutil.rmtree(Path(checkpoints.root) / name)
