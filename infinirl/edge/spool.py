"""The edge's outbox of collected episodes: kept until the cloud acknowledges them, bounded.

On disk (``folder`` given) each episode is one file written atomically (``<seq>.<id>.episode``), so
an edge restarted after a crash or a power loss (``durable=True``) resends what the cloud had not
acknowledged; in memory (``folder=None``) the episodes survive link outages but not the process.
At ``max_bytes`` (or ``max_episodes``) a new episode is refused with :class:`SpoolFullError`: the
caller decides whether the robot pauses or drops it; nothing is discarded silently. An episode larger
than one frame of the link may carry is refused too (:class:`EpisodeTooLargeError`), as it could never
be sent. Opening a folder checks each file's name, header and length against the episode it should
hold (:func:`~infinirl.edge.codec.check_episode_file`); a file that fails (torn by a crash of a
spool that was not ``durable``, or written by something else) is moved to ``corrupt/`` with a
warning, since sending it would only take a slot of the window on every link.
"""

from __future__ import annotations

import logging
import os
import threading
from collections import OrderedDict
from pathlib import Path

from infinirl.edge.codec import check_episode_file
from infinirl.edge.frames import MAX_PAYLOAD_BYTES
from infinirl.utils import atomic_open

__all__ = ["CORRUPT_FOLDER", "EpisodeSpool", "EpisodeTooLargeError", "SpoolFullError"]

logger = logging.getLogger(__name__)

_SUFFIX = ".episode"
CORRUPT_FOLDER = "corrupt"


class SpoolFullError(RuntimeError):
    """The spool holds as much as it may; the link has been down (or slow) for too long."""


class EpisodeTooLargeError(SpoolFullError):
    """An episode larger than a frame of the link may carry. A :class:`SpoolFullError`, so callers
    that count refused episodes and let the robot keep its pace handle it the same way."""


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
        self.set_aside: list[str] = []  # files moved to corrupt/ when the folder was opened
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            for stale in self.folder.glob(f".*{_SUFFIX}.*.tmp"):  # atomic_open's, of a write a crash cut off
                stale.unlink(missing_ok=True)
            for path in sorted(self.folder.glob(f"*{_SUFFIX}")):
                try:
                    episode_id, seq, size = self._check(path)
                except (ValueError, OSError) as exc:
                    self._set_aside(path, exc)
                    continue
                self._entries[episode_id] = (size, seq)
                self.bytes += size
                self._seq = max(self._seq, seq + 1)

    @staticmethod
    def _check(path: Path) -> tuple[str, int, int]:
        seq_text, _, rest = path.name.partition(".")
        if not seq_text.isdigit() or not rest.endswith(_SUFFIX):
            raise ValueError("not a spool file name (<seq>.<episode id>.episode)")
        episode_id, size = rest[:-len(_SUFFIX)], path.stat().st_size
        if size > MAX_PAYLOAD_BYTES:
            raise ValueError(f"{size} bytes, more than a frame of the link carries ({MAX_PAYLOAD_BYTES})")
        with open(path, "rb") as handle:
            inside = check_episode_file(handle, size)
        if inside != episode_id:
            raise ValueError(f"holds episode {inside!r}, its name says {episode_id!r}")
        return episode_id, int(seq_text), size

    def _set_aside(self, path: Path, why: Exception) -> None:
        corrupt = self.folder / CORRUPT_FOLDER
        corrupt.mkdir(exist_ok=True)
        os.replace(path, corrupt / path.name)
        self.set_aside.append(path.name)
        logger.warning("edge spool %s: %s is not a whole episode (%s); moved to %s, it will not be sent",
                       self.folder, path.name, why, corrupt)

    def __len__(self) -> int:
        return len(self._entries)

    def _path(self, episode_id: str, seq: int) -> Path:
        return self.folder / f"{seq:012d}.{episode_id}{_SUFFIX}"

    def put(self, episode_id: str, payload: bytes) -> None:
        if "/" in episode_id or not episode_id:
            raise ValueError(f"episode id {episode_id!r} must be non-empty and contain no '/'")
        if len(payload) > MAX_PAYLOAD_BYTES:  # kept, it would fail every send and hold the spool's head
            raise EpisodeTooLargeError(f"episode {episode_id} is {len(payload)} bytes encoded, more than a frame of "
                                       f"the link carries ({MAX_PAYLOAD_BYTES}); it is not kept: record shorter "
                                       "episodes or smaller camera frames (--frame-size, edge.frame_format)")
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
        """The episode's bytes; None when it is not (or no longer) here."""
        with self._lock:
            entry = self._entries.get(episode_id)
        if entry is None:
            return None
        if self.folder is None:
            return entry[1]
        try:
            return self._path(episode_id, entry[1]).read_bytes()
        except FileNotFoundError:
            with self._lock:
                if self._entries.get(episode_id) != entry:  # acknowledged (removed) while it was being read
                    return None
                # Deleted behind the spool's back: forgotten, else its sender would try it again and again.
                self._entries.pop(episode_id)
                self.bytes -= entry[0]
            logger.warning("edge spool %s: the file of episode %s is gone; it will not be sent", self.folder,
                           episode_id)
            return None

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
