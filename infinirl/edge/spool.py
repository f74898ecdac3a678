"""The edge's outbox of collected episodes: kept until the cloud acknowledges them, bounded.

On disk (``folder`` given) each episode is one file written atomically (``<seq>.<id>.episode``), so
an edge restarted after a crash or a power loss (``durable=True``) resends what the cloud had not
acknowledged; in memory (``folder=None``) the episodes survive link outages but not the process.
At ``max_bytes`` (or ``max_episodes``) a new episode is refused with :class:`SpoolFullError`: the
caller decides whether the robot pauses or drops it; nothing is discarded silently.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from pathlib import Path

from infinirl.utils import atomic_open

__all__ = ["EpisodeSpool", "SpoolFullError"]

_SUFFIX = ".episode"


class SpoolFullError(RuntimeError):
    """The spool holds as much as it may; the link has been down (or slow) for too long."""


class EpisodeSpool:
    """Ordered ``episode_id -> encoded episode`` awaiting acknowledgement (see the module docstring)."""

    def __init__(self, folder: str | os.PathLike | None = None, *, max_bytes: int = 2 << 30,
                 max_episodes: int | None = None, durable: bool = False) -> None:
        self.folder = Path(folder) if folder is not None else None
        self.max_bytes, self.max_episodes, self.durable = max_bytes, max_episodes, durable
        self._lock = threading.Lock()
        self._entries: OrderedDict[str, tuple[int, int | bytes]] = OrderedDict()  # id -> (size, seq or payload)
        self._seq = 0
        self.bytes = 0
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            for path in sorted(self.folder.glob(f"*{_SUFFIX}")):
                seq_text, _, rest = path.name.partition(".")
                seq = int(seq_text)
                self._entries[rest[:-len(_SUFFIX)]] = (path.stat().st_size, seq)
                self.bytes += path.stat().st_size
                self._seq = max(self._seq, seq + 1)

    def __len__(self) -> int:
        return len(self._entries)

    def _path(self, episode_id: str, seq: int) -> Path:
        return self.folder / f"{seq:012d}.{episode_id}{_SUFFIX}"

    def put(self, episode_id: str, payload: bytes) -> None:
        if "/" in episode_id or not episode_id:
            raise ValueError(f"episode id {episode_id!r} must be non-empty and contain no '/'")
        with self._lock:
            if self.bytes + len(payload) > self.max_bytes or (self.max_episodes is not None
                                                               and len(self._entries) >= self.max_episodes):
                where = self.folder if self.folder is not None else "memory"
                raise SpoolFullError(f"edge episode spool ({where}) is full: {len(self._entries)} episodes, "
                                     f"{self.bytes} bytes (max_bytes {self.max_bytes}, max_episodes "
                                     f"{self.max_episodes}); the cloud has not acknowledged them; restore the link "
                                     "or raise the spool's bounds")
            seq, self._seq = self._seq, self._seq + 1
            if self.folder is not None:
                with atomic_open(self._path(episode_id, seq), "wb", durable=self.durable) as handle:
                    handle.write(payload)
                self._entries[episode_id] = (len(payload), seq)
            else:
                self._entries[episode_id] = (len(payload), payload)
            self.bytes += len(payload)

    def ids(self) -> list[str]:
        """Pending episode ids, oldest first."""
        with self._lock:
            return list(self._entries)

    def read(self, episode_id: str) -> bytes | None:
        with self._lock:
            entry = self._entries.get(episode_id)
        if entry is None:
            return None
        if self.folder is None:
            return entry[1]
        return self._path(episode_id, entry[1]).read_bytes()

    def remove(self, episode_id: str) -> bool:
        """Forget an acknowledged episode; False when it was not here (a repeated ack)."""
        with self._lock:
            entry = self._entries.pop(episode_id, None)
            if entry is None:
                return False
            self.bytes -= entry[0]
        if self.folder is not None:
            self._path(episode_id, entry[1]).unlink(missing_ok=True)
        return True
