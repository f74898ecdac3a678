"""One segment of the store: a folder holding one file per field and a commit log.

Layout of ``segments/<number>/``::

    <field>.bin    rows of the field, episode after episode (raw, C order, the declared dtype)
    episodes.log   one checksummed record per committed episode (see ``log.py``)
    sealed.json    written (atomically, durably) once the segment is full: counts, file sizes and
                   the log's crc32; a segment without it is the open (active) one

Only the writer process appends; it writes an episode's field data, then its log record. Reading
maps the field files (``mmap``) or loads them into RAM (for the cache); both check an episode's
per-field crc32 before its rows are first used (:meth:`Segment.verify`).
"""

from __future__ import annotations

import json
import mmap
import os
import zlib
from collections.abc import Mapping

import numpy as np

from infinirl.realworld.replay.log import (
    EpisodeRecord,
    ReplayCorruptionError,
    encode_record,
    record_size,
    scan_records,
)
from infinirl.realworld.replay.spec import EpisodeSpec
from infinirl.utils.atomic import atomic_open, fsync_directory

__all__ = ["LOG_NAME", "SEALED_NAME", "Segment", "fsync_directory"]

LOG_NAME = "episodes.log"
SEALED_NAME = "sealed.json"


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view:
        view = view[os.write(fd, view):]


class _Shifted:
    """Rows ``offset..`` of a field, addressed by their row number in the file."""

    def __init__(self, array: np.ndarray, offset: int):
        self.array, self.offset = array, offset

    def __getitem__(self, rows: slice) -> np.ndarray:
        return self.array[rows.start - self.offset:rows.stop - self.offset]


class Segment:
    """The committed episodes of one segment folder and views of their rows."""

    def __init__(self, path: str, number: int, spec: EpisodeSpec):
        self.path, self.number, self.spec = path, number, spec
        self.names = list(spec.fields)
        self.steps = np.zeros(0, np.int64)
        self.episode_ids = np.zeros(0, np.int64)
        self.first_positions = np.zeros(0, np.int64)
        self.crcs = np.zeros((0, len(self.names)), np.uint32)
        self.sealed = False
        self.log_bytes = 0
        self.verified = np.zeros(0, bool)
        self._maps: dict[str, tuple[int, np.ndarray]] = {}  # field -> (rows mapped, view)
        self._fds: dict[str, int] | None = None  # the writer's append descriptors (field files + log)
        # A failed append whose bytes could not be cut off: they sit where the next episode's rows
        # would go, so the next append cuts them first (and refuses to write if it still cannot).
        self._dirty_tail = False

    # ------------------------------------------------------------------ geometry
    def file(self, name: str) -> str:
        return os.path.join(self.path, f"{name}.bin")

    @property
    def num_episodes(self) -> int:
        return len(self.steps)

    @property
    def transitions(self) -> int:
        return int(self.steps.sum())

    def rows(self, name: str) -> int:
        """Committed rows of field ``name``."""
        return self.transitions + (self.num_episodes if name in self.spec.observations else 0)

    def row_starts(self, name: str) -> np.ndarray:
        """First row of every episode in field ``name``'s file."""
        extra = 1 if name in self.spec.observations else 0
        lengths = self.steps + extra
        return np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64) if len(lengths) else lengths

    @property
    def data_bytes(self) -> int:
        return sum(self.rows(n) * self.spec.row_bytes(n) for n in self.names)

    @property
    def disk_bytes(self) -> int:
        return self.data_bytes + self.log_bytes

    def _add_records(self, records: list[EpisodeRecord], verified: bool) -> None:
        if not records:
            return
        self.steps = np.concatenate([self.steps, [r.steps for r in records]]).astype(np.int64)
        self.episode_ids = np.concatenate([self.episode_ids, [r.episode_id for r in records]]).astype(np.int64)
        self.first_positions = np.concatenate([self.first_positions,
                                               [r.first_position for r in records]]).astype(np.int64)
        self.crcs = np.concatenate([self.crcs, np.array([r.crcs for r in records], np.uint32)])
        self.verified = np.concatenate([self.verified, np.full(len(records), verified)])
        self.log_bytes += len(records) * record_size(len(self.names))

    # ------------------------------------------------------------------ opening
    @classmethod
    def create(cls, path: str, number: int, spec: EpisodeSpec, durable: bool) -> Segment:
        os.makedirs(path)
        segment = cls(path, number, spec)
        segment._open_for_append()
        if durable:
            fsync_directory(path)
            fsync_directory(os.path.dirname(path))
        return segment

    @classmethod
    def open(cls, path: str, number: int, spec: EpisodeSpec, writable: bool) -> Segment:
        """A sealed segment (checked against ``sealed.json``) or the open one: a writer cuts a
        torn tail off its log and field files; a reader sees the complete records only."""
        segment = cls(path, number, spec)
        log_path = os.path.join(path, LOG_NAME)
        # Looked at before the log is read: the writer seals after its last record, so a segment
        # sealed by then has its final log; one sealed while a reader reads it is taken as open
        # (its next refresh sees the seal), never as a sealed log cut short.
        sealed_path = os.path.join(path, SEALED_NAME)
        sealed = os.path.exists(sealed_path)
        data = b""
        if os.path.exists(log_path):  # absent only in a segment whose creation was interrupted
            with open(log_path, "rb") as handle:
                data = handle.read()
        records, span = scan_records(data, len(segment.names), log_path)
        segment._add_records(records, verified=False)
        if sealed:
            segment._check_sealed(sealed_path, data)
        elif writable:
            segment._cut_torn_tail(log_path, span)
        segment._check_field_sizes(exact=segment.sealed)
        if writable and not segment.sealed:
            segment._open_for_append()
        if not writable:
            # The writer may evict (unlink) the segment at any time; a reader's maps keep its data
            # readable until the reader's next refresh drops it from the view.
            segment.mapped()
        return segment

    def _check_sealed(self, sealed_path: str, log_data: bytes) -> None:
        with open(sealed_path, encoding="utf-8") as handle:
            meta = json.load(handle)
        if (len(log_data) != meta["log_bytes"] or zlib.crc32(log_data) != meta["log_crc32"]
                or self.num_episodes != meta["episodes"]):
            raise ReplayCorruptionError(f"{os.path.join(self.path, LOG_NAME)}: the commit log of a sealed segment "
                                        f"differs from {SEALED_NAME} (size or crc32); restore the segment from a copy "
                                        f"or move its folder out of the store")
        self.sealed = True

    def _cut_torn_tail(self, log_path: str, span: int) -> None:
        if os.path.exists(log_path) and os.path.getsize(log_path) > span:
            os.truncate(log_path, span)
        for name in self.names:
            committed = self.rows(name) * self.spec.row_bytes(name)
            if os.path.exists(self.file(name)) and os.path.getsize(self.file(name)) > committed:
                os.truncate(self.file(name), committed)  # rows of the episode that was being written

    def _check_field_sizes(self, exact: bool) -> None:
        for name in self.names:
            committed = self.rows(name) * self.spec.row_bytes(name)
            size = os.path.getsize(self.file(name)) if os.path.exists(self.file(name)) else 0
            if size < committed or (exact and size != committed):
                raise ReplayCorruptionError(f"{self.file(name)}: {size} bytes, the commit log says {committed}; the "
                                            f"segment is damaged: restore it from a copy or move its folder out")

    def refresh(self) -> int:
        """A reader's look at the open segment: take the records committed since; returns how many
        (and whether it got sealed meanwhile, in :attr:`sealed`)."""
        log_path = os.path.join(self.path, LOG_NAME)
        sealed = os.path.exists(os.path.join(self.path, SEALED_NAME))
        with open(log_path, "rb") as handle:
            handle.seek(self.log_bytes)
            data = handle.read()
        records, _ = scan_records(data, len(self.names), log_path)
        self._add_records(records, verified=False)
        self.sealed = sealed
        return len(records)

    # ------------------------------------------------------------------ writing
    def _open_for_append(self) -> None:
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND
        self._fds = {name: os.open(self.file(name), flags, 0o644) for name in self.names}
        self._fds[LOG_NAME] = os.open(os.path.join(self.path, LOG_NAME), flags, 0o644)

    def append(self, steps: int, arrays: Mapping[str, np.ndarray], episode_id: int, first_position: int,
               durable: bool) -> None:
        """Write one checked episode: field data first, then (once that is on disk) its commit record.

        A write or fsync that fails (a full disk, an I/O error) cuts every file back to its committed
        bytes before the error propagates: the commit records place each episode right after the
        previous one's rows, so bytes of a failed episode left in a file would shift every later
        episode's rows (and this process does not check the crc32 of the episodes it wrote)."""
        assert self._fds is not None, "append on a segment that is not open for writing"
        if self._dirty_tail:
            self._cut_to_committed()
        crcs = []
        try:
            for name in self.names:
                _write_all(self._fds[name], arrays[name])
                crcs.append(zlib.crc32(arrays[name]))
            if durable:
                for name in self.names:
                    os.fdatasync(self._fds[name])
            record = EpisodeRecord(steps=steps, episode_id=episode_id, first_position=first_position,
                                   crcs=tuple(crcs))
            _write_all(self._fds[LOG_NAME], encode_record(record))
            if durable:  # an fsync error may have dropped the record: it is cut off and the append fails
                os.fdatasync(self._fds[LOG_NAME])
        except BaseException as exc:
            try:
                self._cut_to_committed()
            except OSError as cut:
                exc.add_note(f"{self.path}: cutting the failed episode's bytes off failed too ({cut!r}); the next "
                             f"append tries again before it writes")
            raise
        self._add_records([record], verified=True)  # this process computed the crcs from the rows it wrote

    def _cut_to_committed(self) -> None:
        """Truncate every field file and the log to the bytes of the committed episodes (all there is
        of a segment whose appends all succeeded, as its torn tail is cut on open)."""
        self._dirty_tail = True
        for name in self.names:
            os.ftruncate(self._fds[name], self.rows(name) * self.spec.row_bytes(name))
        os.ftruncate(self._fds[LOG_NAME], self.log_bytes)
        self._dirty_tail = False

    def seal(self, durable: bool) -> None:
        """Publish the segment as complete: ``sealed.json`` written atomically after the data. The
        append descriptors stay open until it is in place, so after a failed seal the segment stays
        open and the next append (which seals again) goes on writing."""
        assert self._fds is not None, "seal on a segment that is not open for writing"
        log_path = os.path.join(self.path, LOG_NAME)
        sealed_path = os.path.join(self.path, SEALED_NAME)
        with open(log_path, "rb") as handle:
            log_data = handle.read()
        meta = {"episodes": self.num_episodes, "transitions": self.transitions, "log_bytes": len(log_data),
                "log_crc32": zlib.crc32(log_data),
                "field_bytes": {n: self.rows(n) * self.spec.row_bytes(n) for n in self.names}}
        try:
            if durable:
                for fd in self._fds.values():
                    os.fsync(fd)
            with atomic_open(sealed_path, "w", durable=durable) as handle:
                json.dump(meta, handle)
            if durable:
                fsync_directory(self.path)
        finally:
            # Once sealed.json is in place (even if a folder fsync after its rename failed) a reopen
            # takes the segment as sealed against it: no episode may be appended to it any more.
            if os.path.exists(sealed_path):
                self.sealed = True
                fds, self._fds = self._fds, None
                for fd in fds.values():
                    os.close(fd)

    def unmap(self) -> None:
        """Drop this process's memory maps of the field files (remapped on the next read)."""
        self._maps.clear()

    def close(self) -> None:
        for fd in (self._fds or {}).values():
            os.close(fd)
        self._fds = None
        self._maps.clear()

    # ------------------------------------------------------------------ reading
    def mapped(self) -> dict[str, np.ndarray]:
        """``field -> [committed rows, *shape]`` arrays over memory maps of the files (no copy)."""
        out = {}
        for name in self.names:
            rows = self.rows(name)
            have = self._maps.get(name)
            if have is None or have[0] < rows:
                have = (rows, self._map(name, rows))
                self._maps[name] = have
            out[name] = have[1][:rows]
        return out

    def _map(self, name: str, rows: int) -> np.ndarray:
        shape, dtype = self.spec.fields[name]
        length = rows * self.spec.row_bytes(name)
        if length == 0:
            return np.zeros((rows, *shape), dtype)
        fd = os.open(self.file(name), os.O_RDONLY)
        try:
            buffer = mmap.mmap(fd, length, access=mmap.ACCESS_READ)
        finally:
            os.close(fd)  # the map keeps the file alive, even once the writer evicts it
        return np.frombuffer(buffer, dtype=dtype).reshape(rows, *shape)

    def load(self, first_episode: int = 0) -> dict[str, np.ndarray]:
        """The committed rows of the episodes from ``first_episode`` on, read into RAM and checked
        against the commit log (for the cache)."""
        arrays = {}
        for name in self.names:
            shape, dtype = self.spec.fields[name]
            start = int(self.row_starts(name)[first_episode]) if first_episode < self.num_episodes else self.rows(name)
            mapped = self._maps.get(name)
            if mapped is not None and mapped[0] >= self.rows(name):  # a reader's map: the file may be gone
                arrays[name] = np.array(mapped[1][start:self.rows(name)])
                continue
            array = np.empty((self.rows(name) - start, *shape), dtype)
            with open(self.file(name), "rb", buffering=0) as handle:
                handle.seek(start * self.spec.row_bytes(name))
                view, done = memoryview(array.reshape(-1).view(np.uint8)), 0
                while done < len(view):
                    got = handle.readinto(view[done:])
                    if not got:
                        raise ReplayCorruptionError(f"{self.file(name)}: shorter than its commit log says")
                    done += got
            arrays[name] = array
        self._verify_from(first_episode, arrays)
        return arrays

    def _verify_from(self, first_episode: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Check the episodes from ``first_episode`` on against rows that start at that episode."""
        full = {}
        for name in self.names:  # index as if the rows began at row 0 of the file
            offset = int(self.row_starts(name)[first_episode]) if first_episode < self.num_episodes else 0
            full[name] = _Shifted(arrays[name], offset)
        self.verify(np.arange(first_episode, self.num_episodes), full)

    def verify(self, episodes: np.ndarray, arrays: Mapping[str, np.ndarray]) -> None:
        """Check the crc32 of every field of the local ``episodes`` not checked yet; raises naming the file."""
        todo = [int(e) for e in episodes if not self.verified[e]]
        if not todo:
            return
        starts = {name: self.row_starts(name) for name in self.names}
        for e in todo:
            for j, name in enumerate(self.names):
                start = starts[name][e]
                rows = arrays[name][start:start + self.spec.rows(name, int(self.steps[e]))]
                if zlib.crc32(np.ascontiguousarray(rows)) != int(self.crcs[e, j]):
                    raise ReplayCorruptionError(
                        f"{self.file(name)}: episode {int(self.episode_ids[e])} (rows {start}..{start + len(rows)}) "
                        f"fails its crc32; the segment is damaged: restore it from a copy or move its folder out")
            self.verified[e] = True

    def episode(self, local: int, arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        self.verify(np.array([local]), arrays)
        out = {}
        for name in self.names:
            start = int(self.row_starts(name)[local])
            out[name] = np.array(arrays[name][start:start + self.spec.rows(name, int(self.steps[local]))])
        return out
