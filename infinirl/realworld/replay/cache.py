"""A least-recently-used cache bounded by bytes: the RAM copies of the hottest segments."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from typing import Any

__all__ = ["ByteLRU"]


class ByteLRU:
    """Holds values with a byte size; ``put`` evicts the least recently used until the total fits
    ``capacity_bytes``; a value larger than the capacity is not kept. ``get`` marks a value used."""

    def __init__(self, capacity_bytes: int):
        if capacity_bytes < 0:
            raise ValueError(f"cache capacity must be >= 0 bytes, got {capacity_bytes}")
        self.capacity_bytes = int(capacity_bytes)
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self.nbytes = 0

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def __len__(self) -> int:
        return len(self._items)

    def keys(self) -> list:
        """Keys, least recently used first."""
        return list(self._items)

    def get(self, key: Hashable) -> Any | None:
        item = self._items.get(key)
        if item is None:
            return None
        self._items.move_to_end(key)
        return item[0]

    def put(self, key: Hashable, value: Any, nbytes: int) -> bool:
        """Keep ``value`` as the most recently used; returns whether it was kept."""
        self.pop(key)
        if nbytes > self.capacity_bytes:
            return False
        while self.nbytes + nbytes > self.capacity_bytes:
            self.pop(next(iter(self._items)))
        self._items[key] = (value, int(nbytes))
        self.nbytes += int(nbytes)
        return True

    def pop(self, key: Hashable) -> None:
        item = self._items.pop(key, None)
        if item is not None:
            self.nbytes -= item[1]

    def fits(self, nbytes: int) -> bool:
        """Whether ``nbytes`` more fit without evicting anything."""
        return self.nbytes + nbytes <= self.capacity_bytes
