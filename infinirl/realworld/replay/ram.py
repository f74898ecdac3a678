"""RAM copies of a segment's rows: what the cache holds. The open segment's copy grows as
episodes are appended (capacity doubles, so appends copy each row about once)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

__all__ = ["RowArrays"]


class RowArrays:
    """``field -> array`` with room to grow; :meth:`view` gives the filled rows."""

    def __init__(self, arrays: Mapping[str, np.ndarray]):
        self._arrays = dict(arrays)
        self._rows = {name: len(array) for name, array in self._arrays.items()}

    @property
    def nbytes(self) -> int:
        """Bytes allocated (filled rows and the room to grow)."""
        return sum(array.nbytes for array in self._arrays.values())

    def view(self) -> dict[str, np.ndarray]:
        return {name: array[:self._rows[name]] for name, array in self._arrays.items()}

    def extend(self, rows: Mapping[str, np.ndarray]) -> None:
        for name, new in rows.items():
            have, array = self._rows[name], self._arrays[name]
            if have + len(new) > len(array):
                grown = np.empty((max(2 * len(array), have + len(new)), *array.shape[1:]), array.dtype)
                grown[:have] = array[:have]
                self._arrays[name] = array = grown
            array[have:have + len(new)] = new
            self._rows[name] = have + len(new)

    def trim(self) -> None:
        """Give back the room to grow (a sealed segment does not grow)."""
        self._arrays = {name: array[:self._rows[name]].copy() if len(array) > self._rows[name] else array
                        for name, array in self._arrays.items()}
