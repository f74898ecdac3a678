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
import queue
import tempfile
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from infinirl.realworld.intervention.device import EPISODE_MARKS

__all__ = ["REWARD_SOURCES", "BackgroundLabelWriter", "HumanOutcome", "SuccessLabelWriter", "human_reward",
           "success_labels"]

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


class BackgroundLabelWriter:
    """A :class:`SuccessLabelWriter` on a thread of its own, for the robot's control thread.

    Why: a mark given with ``reward=env`` does not end the episode, and stacking and compressing a
    camera episode's frames takes a sizeable fraction of a second: on the control thread that makes
    steps late and can trip the safety watchdog. :meth:`submit` only snapshots the rows (lists of the
    recorded arrays, which are not changed after recording) and queues them; at most ``max_pending``
    wait, after which it blocks up to ``submit_timeout_s`` (a disk that slow must not grow memory
    without bound). A write that failed is raised by the next :meth:`submit` or by :meth:`close`,
    which writes what is queued first."""

    def __init__(self, folder: str, prefix: str = "labels", max_pending: int = 4, submit_timeout_s: float = 60.0):
        self.writer = SuccessLabelWriter(folder, prefix)
        self.submit_timeout_s = submit_timeout_s
        self.written: list[str] = []
        self._queue: queue.Queue = queue.Queue(maxsize=max_pending)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"labels-{prefix}", daemon=True)
        self._thread.start()

    def submit(self, observations: Mapping[str, Sequence[np.ndarray]], mark: str) -> None:
        self._raise_failure()
        snapshot = {key: list(values) for key, values in observations.items()}
        try:
            self._queue.put((snapshot, mark), timeout=self.submit_timeout_s)
        except queue.Full:
            raise RuntimeError(f"success labels: {self._queue.maxsize} episodes still wait to be written to "
                               f"{self.writer.folder} after {self.submit_timeout_s:.0f} s: is the disk full or "
                               "very slow?") from None

    def close(self, timeout_s: float = 60.0) -> None:
        """Write what is queued, stop the thread, raise a failed write."""
        if self._thread.is_alive():
            try:
                self._queue.put(None, timeout=timeout_s)
            except queue.Full:
                pass
            self._thread.join(timeout_s)
        self._raise_failure()

    def _raise_failure(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"success labels: writing to {self.writer.folder} failed: {self._error!r}") \
                from self._error

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is not None:
                continue  # reported already by the next submit or close; nothing more is written
            try:
                self.written.append(self.writer.write(*item))
            except BaseException as exc:  # noqa: BLE001 - kept for the control thread to raise
                self._error = exc
