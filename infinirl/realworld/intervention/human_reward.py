"""Human reward: the person's success / failure mark becomes the episode's reward, and labels frames
for a learned success classifier.

With the reward source ``human`` the robot worker replaces the env's reward by :func:`human_reward`:
0 on every step, then, when a mark arrives, ``success`` gives the step that led to the marked state 1
(``failure`` 0) and ends the episode there (``terminated``: the human said the episode is over). An
episode the human never marks ends at its step limit with all rewards 0 (and still bootstraps).

A mark also labels the episode's observations up to the marked one (:func:`success_labels`): the
marked observation is a success (1) after a ``success`` mark, every other one a non-success (0).
:class:`SuccessLabelWriter` saves them as one ``.npz`` per marked episode (``state``, each
``pixels.<camera>``, ``label`` int8), written atomically, for training a success classifier.
"""

from __future__ import annotations

import io
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from infinirl.realworld.intervention.device import EPISODE_MARKS

__all__ = ["REWARD_SOURCES", "HumanOutcome", "SuccessLabelWriter", "human_reward", "success_labels"]

REWARD_SOURCES = ("env", "human")
MARK_REWARD = {"success": 1.0, "failure": 0.0}


@dataclass(frozen=True, kw_only=True)
class HumanOutcome:
    """What a mark does to the step that led to the marked state."""

    reward: float
    terminated: bool
    success: bool


def human_reward(marks: Sequence[str]) -> HumanOutcome | None:
    """The outcome of the marks given since the last step, or None when there is none. With several
    marks the last one counts (a person who corrects a mis-click)."""
    if not marks:
        return None
    mark = marks[-1]
    if mark not in EPISODE_MARKS:
        raise ValueError(f"unknown episode mark {mark!r}; known: {list(EPISODE_MARKS)}")
    return HumanOutcome(reward=MARK_REWARD[mark], terminated=True, success=mark == "success")


def success_labels(num_observations: int, mark: str) -> np.ndarray:
    """Labels (int8) of an episode's first ``num_observations`` observations, the last being the
    marked one: 1 for it after a ``success`` mark, 0 for every other."""
    if mark not in EPISODE_MARKS:
        raise ValueError(f"unknown episode mark {mark!r}; known: {list(EPISODE_MARKS)}")
    labels = np.zeros(num_observations, np.int8)
    if mark == "success" and num_observations:
        labels[-1] = 1
    return labels


class SuccessLabelWriter:
    """Writes labelled observations under ``folder`` as ``<prefix>-<n>.npz`` (n counts up from the
    highest index already there, so a restarted worker adds to them, even after some were deleted;
    a file is never replaced: a name already taken is skipped)."""

    def __init__(self, folder: str, prefix: str = "labels") -> None:
        self.folder, self.prefix = folder, prefix
        os.makedirs(folder, exist_ok=True)
        self.count = self._next_index()

    def _next_index(self) -> int:
        """One past the highest ``<prefix>-<n>.npz`` index in the folder (0 when none)."""
        highest = -1
        head, tail = f"{self.prefix}-", ".npz"
        for name in os.listdir(self.folder):
            index = name[len(head):-len(tail)] if name.startswith(head) and name.endswith(tail) else ""
            if index.isdigit():
                highest = max(highest, int(index))
        return highest + 1

    def write(self, observations: Mapping[str, Sequence[np.ndarray]], mark: str) -> str:
        rows = {key: np.stack([np.asarray(v) for v in values]) for key, values in observations.items()}
        num = len(next(iter(rows.values())))
        buffer = io.BytesIO()
        np.savez(buffer, label=success_labels(num, mark), **rows)
        handle = tempfile.NamedTemporaryFile(dir=self.folder, prefix=f".{self.prefix}-", suffix=".tmp", delete=False)
        try:
            with handle:
                handle.write(buffer.getvalue())
            while True:
                path = os.path.join(self.folder, f"{self.prefix}-{self.count:06d}.npz")
                try:
                    # A hard link appears whole and fails rather than replacing a file already
                    # there (another writer with this prefix, or a file written since start-up).
                    os.link(handle.name, path)
                except FileExistsError:
                    self.count += 1
                    continue
                break
        finally:
            os.unlink(handle.name)
        self.count += 1
        return path
