"""Which source id (e.g. an edge's episode id) each stored episode came from, so a resend is stored once.

``sources.log`` in the store's folder holds one line ``<episode id> <source id>`` per episode
appended with a source id. The line is written (and in a durable store fsynced) *before* the
episode is committed, naming the episode id the store is about to give it. A process killed between
the two leaves a line for an episode id that was never committed: reopening for writing drops such
lines, and a later line for the same episode id overrides an earlier one (the last line wins; a
line with the episode id alone cancels, written when an append failed without a crash). So
after any crash the log names exactly the sources of the committed episodes, and a sender that
resends an episode it was not told was stored (an edge after an outage) finds it stored once.
"""

from __future__ import annotations

import os

from infinirl.utils.atomic import atomic_open, fsync_directory

__all__ = ["SOURCES_NAME", "SourceLog"]

SOURCES_NAME = "sources.log"


def check_source_id(source_id: str) -> None:
    if not source_id or any(c.isspace() for c in source_id):
        raise ValueError(f"replay source id {source_id!r} must be non-empty and contain no whitespace")


def _read_lines(path: str) -> tuple[list[tuple[int, str]], bool]:
    """``(entries, torn)``: the complete lines of the log, and whether a partial last line followed."""
    if not os.path.exists(path):
        return [], False
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    lines = text.split("\n")
    torn = lines[-1] != ""  # a write cut short: never committed (its episode's append had not begun)
    entries = []
    for line in lines[:-1]:
        number, _, source = line.partition(" ")
        entries.append((int(number), source))
    return entries, torn


class SourceLog:
    """The committed episodes' source ids (see the module docstring). ``committed``: how many
    episodes the store holds (its ids are ``0 .. committed - 1``)."""

    def __init__(self, folder: str, committed: int, *, writable: bool, durable: bool) -> None:
        self.path = os.path.join(folder, SOURCES_NAME)
        self.durable = durable
        entries, torn = _read_lines(self.path)
        by_episode = {number: source for number, source in entries}  # the last line per episode id wins
        kept = {number: source for number, source in by_episode.items() if number < committed and source}
        self._episode_of = {source: number for number, source in sorted(kept.items())}
        self._fd: int | None = None
        if writable:
            if torn or len(kept) != len(entries):  # drop the torn tail and the never-committed lines
                with atomic_open(self.path, "w", durable=durable) as handle:
                    handle.writelines(f"{number} {source}\n" for number, source in sorted(kept.items()))
            created = not os.path.exists(self.path)
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
            if created and durable:  # the new name lives in the folder: without this a power loss may drop the log
                fsync_directory(folder)

    def __len__(self) -> int:
        return len(self._episode_of)

    def episode_of(self, source_id: str) -> int | None:
        """The store's episode id of ``source_id``'s episode, or None when it is not stored."""
        return self._episode_of.get(source_id)

    def sources(self) -> dict[str, int]:
        """``source id -> episode id`` of every committed episode that has one."""
        return dict(self._episode_of)

    def intend(self, source_id: str, episode_id: int) -> None:
        """Record that ``episode_id``, about to be committed, comes from ``source_id`` (before the commit)."""
        check_source_id(source_id)
        data = f"{episode_id} {source_id}\n".encode()
        self._write(data)
        self._episode_of[source_id] = episode_id

    def forget(self, source_id: str) -> None:
        """The append after :meth:`intend` failed without committing: cancel its line."""
        episode_id = self._episode_of.pop(source_id, None)
        if episode_id is not None:
            self._write(f"{episode_id}\n".encode())

    def _write(self, data: bytes) -> None:
        size = os.fstat(self._fd).st_size
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view):]
            if self.durable:
                os.fsync(self._fd)
        except BaseException:
            # A part of a line would run into the next line written; a whole line whose fsync failed
            # would name a source for an episode id that a later append may give to another episode.
            os.ftruncate(self._fd, size)
            raise

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
