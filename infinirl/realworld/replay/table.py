"""The in-RAM index of every live episode: where a transition's rows are, in O(log episodes).

One row per episode (six int64), so its size grows with the number of episodes and never with
the size of observations. Positions are absolute transition numbers (the ``n``-th transition ever
appended), stable across eviction: the live positions are ``[first_live, end)``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EpisodeTable", "Locations"]

_COLUMNS = ("first_position", "steps", "segment", "local", "obs_start", "step_start")


class Locations:
    """Where sampled transitions live: per transition its segment number, local episode index,
    observation row and step row (all int64 arrays of the batch's length)."""

    def __init__(self, segment: np.ndarray, local: np.ndarray, obs_row: np.ndarray, step_row: np.ndarray):
        self.segment, self.local, self.obs_row, self.step_row = segment, local, obs_row, step_row


class EpisodeTable:
    def __init__(self):
        self._data = np.zeros((len(_COLUMNS), 64), np.int64)
        self._start = 0  # first live row
        self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def column(self, name: str) -> np.ndarray:
        return self._data[_COLUMNS.index(name), self._start:self._end]

    @property
    def first_live(self) -> int:
        """Absolute position of the oldest live transition (0 when empty)."""
        return int(self._data[0, self._start]) if len(self) else self.end_position

    @property
    def end_position(self) -> int:
        """One past the newest transition's absolute position."""
        if self._end == 0:
            return 0
        return int(self._data[0, self._end - 1] + self._data[1, self._end - 1])

    def append(self, first_position: np.ndarray, steps: np.ndarray, segment: int, local: np.ndarray,
               obs_start: np.ndarray, step_start: np.ndarray) -> None:
        n = len(steps)
        if self._end + n > self._data.shape[1]:
            live = self._data[:, self._start:self._end]
            grown = np.zeros((len(_COLUMNS), max(2 * len(self) + n, 64)), np.int64)
            grown[:, :len(self)] = live
            self._data, self._start, self._end = grown, 0, len(self)
        block = self._data[:, self._end:self._end + n]
        block[0], block[1], block[2], block[3], block[4], block[5] = (first_position, steps, segment, local,
                                                                      obs_start, step_start)
        self._end += n

    def drop_segment(self, segment: int) -> None:
        """Forget the oldest segment's episodes (eviction removes the oldest segment only)."""
        segments = self.column("segment")
        self._start += int(np.searchsorted(segments, segment, side="right"))

    def locate(self, positions: np.ndarray) -> Locations:
        """Rows of the absolute ``positions`` (each inside a live episode)."""
        firsts = self.column("first_position")
        episode = np.searchsorted(firsts, positions, side="right") - 1
        offset = positions - firsts[episode]
        rows = self._data[:, self._start:self._end][:, episode]
        return Locations(rows[2], rows[3], rows[4] + offset, rows[5] + offset)
