"""The persistent replay store: episodes on disk in segments, a RAM cache, seeded sampling.

Directory layout (see ``segment.py`` for a segment's folder)::

    store.json          format version and the EpisodeSpec (written once, atomically)
    sources.log         the source id of each episode appended with one (``sources.py``)
    writer.lock         held (flock) by the one writer process; holds its pid
    segments/00000000/  sealed segments, oldest first ...
    segments/0000000N/  ... and the open one the writer appends to (no sealed.json yet)

Guarantees:

* **Append.** ``append`` returns once the episode is committed: its rows are written (and with
  ``durable`` fsynced) and then its checksummed record is in the segment's commit log. A process
  killed at any point (``kill -9``) loses at most the episode being appended; reopening for
  writing cuts the torn tail off the open segment's log and field files and continues. An
  append that raises (a full disk, an I/O error) leaves none of its bytes behind for the next one.
* **Once per source.** An episode appended with a ``source_id`` (a sender's id for it, e.g. an
  edge's episode id) is stored once: appending the same source id again returns the stored
  episode's id and writes nothing, also after a crash and a reopen (:mod:`.sources`), so a sender
  may resend whatever it was not told was committed.
* **Damage.** Every committed episode carries a crc32 per field; it is checked before the
  episode's rows are first used (on loading a segment into the cache, on the first read through
  a memory map) and by :meth:`ReplayStore.verify`. A mismatch raises
  :class:`~infinirl.realworld.replay.log.ReplayCorruptionError` naming the file; nothing is
  dropped silently.
* **Readers.** Other processes may open the same directory with ``writable=False``: they see the
  episodes committed when they opened or last called :meth:`ReplayStore.refresh`, never a partial
  one. A segment the writer evicts stays readable to a reader that already maps it until its
  next ``refresh``.
* **Capacity.** ``max_bytes`` bounds the disk use: after a segment is sealed, the oldest sealed
  segments are deleted until the total fits (the open and the newest sealed segment are kept, so
  the bound may be exceeded by up to about two segments).
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from infinirl.realworld.replay.cache import ByteLRU
from infinirl.realworld.replay.log import ReplayCorruptionError
from infinirl.realworld.replay.ram import RowArrays
from infinirl.realworld.replay.sampler import SamplingSpec, TransitionSampler
from infinirl.realworld.replay.segment import Segment, fsync_directory
from infinirl.realworld.replay.sources import SourceLog
from infinirl.realworld.replay.spec import EpisodeSpec
from infinirl.realworld.replay.table import EpisodeTable
from infinirl.utils.atomic import atomic_open

__all__ = ["ReplayStore", "StoreOptions"]

FORMAT = 1
MIB = 1 << 20
_EVICTING = ".evicting"
_READER_RETRIES = 20  # a reader's listing races the writer's evictions; each retry re-lists


@dataclass(frozen=True, kw_only=True)
class StoreOptions:
    segment_bytes: int = 256 * MIB  # a segment is sealed once its field data reaches this size
    max_bytes: int | None = None  # disk bound; None: keep every episode
    cache_bytes: int = 1024 * MIB  # RAM for copies of the newest segments (the open one included)
    durable: bool = True  # fsync each episode before it counts as committed (survives power loss)
    verify_reads: bool = True  # check an episode's crc32 before its first read through a memory map

    def __post_init__(self):
        if self.segment_bytes < 1:
            raise ValueError(f"replay store segment_bytes must be >= 1, got {self.segment_bytes}")
        if self.max_bytes is not None and self.max_bytes < 1:
            raise ValueError(f"replay store max_bytes must be >= 1 or None, got {self.max_bytes}")
        if self.cache_bytes < 0:
            raise ValueError(f"replay store cache_bytes must be >= 0, got {self.cache_bytes}")


def _segment_dirs(root: str) -> list[tuple[int, str]]:
    folder = os.path.join(root, "segments")
    names = sorted(n for n in os.listdir(folder) if n.isdigit())
    return [(int(n), os.path.join(folder, n)) for n in names]


class ReplayStore:
    """Episodes appended to disk, sampled as ``(obs, action, reward, next_obs, done)`` mini-batches.

    Args:
        path: the store's folder (created by a writer if missing).
        spec: the episode fields; required to create a store, checked against an existing one.
        writable: one writer process per store (others get a one-line error); readers pass False.
        options: :class:`StoreOptions` (segment size, disk bound, cache size, durability).
        sampling: :class:`~infinirl.realworld.replay.sampler.SamplingSpec` (seed, recent weighting).
    """

    def __init__(self, path: str, spec: EpisodeSpec | None = None, *, writable: bool = True,
                 options: StoreOptions | None = None, sampling: SamplingSpec | None = None):
        self.path = os.path.abspath(path)
        self.writable = writable
        self.options = options or StoreOptions()
        self.sampler = TransitionSampler(sampling or SamplingSpec())
        self.cache = ByteLRU(self.options.cache_bytes)
        self.table = EpisodeTable()
        self.segments: dict[int, Segment] = {}
        self.next_episode_id = 0
        self._lock_fd: int | None = None
        self.sources: SourceLog | None = None
        if writable:
            self._lock()
        try:
            self.spec = self._open_spec(spec)
            if writable:
                self._open_segments_for_writing()
            else:
                self.refresh()
            self.sources = SourceLog(self.path, self.next_episode_id, writable=writable, durable=self.options.durable)
            self._warm_cache()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ opening
    def _lock(self) -> None:
        os.makedirs(os.path.join(self.path, "segments"), exist_ok=True)
        lock_path = os.path.join(self.path, "writer.lock")
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            if e.errno in (errno.EAGAIN, errno.EACCES):
                raise RuntimeError(f"{lock_path}: the replay store is open for writing by process {holder}; one writer "
                                   f"per store: open it with writable=False to read") from None
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        self._lock_fd = fd

    def _open_spec(self, spec: EpisodeSpec | None) -> EpisodeSpec:
        meta_path = os.path.join(self.path, "store.json")
        if not os.path.exists(meta_path):
            if not self.writable:
                raise FileNotFoundError(f"{meta_path}: no replay store here (a writer creates it)")
            if spec is None:
                raise ValueError(f"{self.path}: creating a replay store needs an EpisodeSpec")
            with atomic_open(meta_path, "w", durable=self.options.durable) as handle:
                json.dump({"format": FORMAT, "spec": spec.to_json()}, handle, indent=1)
            return spec
        with open(meta_path, encoding="utf-8") as handle:
            meta = json.load(handle)
        if meta.get("format") != FORMAT:
            raise ValueError(f"{meta_path}: replay store format {meta.get('format')}, this code reads {FORMAT}")
        stored = EpisodeSpec.from_json(meta["spec"])
        if spec is not None and spec != stored:
            raise ValueError(f"{meta_path}: the store holds fields {stored.to_json()}, the given spec declares "
                             f"{spec.to_json()}; open it with its own spec (or spec=None) or use a new folder")
        return stored

    def _open_segments_for_writing(self) -> None:
        folder = os.path.join(self.path, "segments")
        for name in os.listdir(folder):
            if name.endswith(_EVICTING):  # an eviction interrupted after its rename: finish it
                shutil.rmtree(os.path.join(folder, name))
        found = _segment_dirs(self.path)
        for i, (number, path) in enumerate(found):
            for leftover in (n for n in os.listdir(path) if n.startswith(".")):  # an interrupted atomic write
                os.unlink(os.path.join(path, leftover))
            segment = Segment.open(path, number, self.spec, writable=True)
            if not segment.sealed and i != len(found) - 1:
                raise ReplayCorruptionError(f"{path}: an unsealed segment before the newest one; move the folder out "
                                            f"of the store if its episodes are not needed")
            self._add_segment(segment)
        self._evict()  # a run stopped between sealing a segment and evicting

    def refresh(self) -> int:
        """Take the episodes committed (and notice the segments evicted) since the last look; returns
        how many episodes came. A reader's view changes only here."""
        for attempt in range(_READER_RETRIES):
            try:
                return self._refresh_once()
            except FileNotFoundError:  # the writer evicted a segment while we were opening it
                if attempt == _READER_RETRIES - 1:
                    raise
                time.sleep(0.01)
        return 0

    def _refresh_once(self) -> int:
        before = self.next_episode_id
        listed = dict(_segment_dirs(self.path))
        for number in [n for n in self.segments if n not in listed]:  # evicted (always the oldest)
            self._forget(number)
        if self.segments:
            newest = self.segments[max(self.segments)]
            if not newest.sealed:
                old = newest.num_episodes
                newest.refresh()
                newest.mapped()  # map the new rows now, while the files surely exist (see Segment.open)
                self._index(newest, old)
                if self._grow_cached(newest, old, None) is None and newest.sealed:
                    self._admit(newest)
        last = max(self.segments) if self.segments else -1
        for number in sorted(n for n in listed if n > last):
            self._add_segment(Segment.open(listed[number], number, self.spec, writable=False))
        return self.next_episode_id - before

    def _add_segment(self, segment: Segment) -> None:
        self.segments[segment.number] = segment
        self._index(segment, 0)

    def _index(self, segment: Segment, start: int) -> None:
        """Put the segment's episodes from local index ``start`` on into the table."""
        if start == segment.num_episodes:
            return
        first = int(segment.first_positions[start])
        if len(self.table) and first != self.table.end_position:
            raise ReplayCorruptionError(f"{segment.path}: its episodes start at transition {first}, the store's "
                                        f"previous segment ends at {self.table.end_position}: a segment is missing")
        obs_name = next(iter(self.spec.observations))
        steps = segment.steps[start:]
        step_starts = np.concatenate([[0], np.cumsum(segment.steps)[:-1]])[start:]
        self.table.append(segment.first_positions[start:], steps, segment.number,
                          np.arange(start, segment.num_episodes), segment.row_starts(obs_name)[start:], step_starts)
        self.next_episode_id = int(segment.episode_ids[-1]) + 1

    def _warm_cache(self) -> None:
        """Load the newest segments (the open one first) into the cache, as many as fit."""
        for number in sorted(self.segments, reverse=True):
            segment = self.segments[number]
            if not self.cache.fits(segment.data_bytes):
                break
            self._admit(segment)

    def _admit(self, segment: Segment) -> None:
        if 0 < segment.data_bytes <= self.cache.capacity_bytes:
            self.cache.put(segment.number, RowArrays(segment.load()), segment.data_bytes)

    def _grow_cached(self, segment: Segment, old: int, rows: Mapping[str, np.ndarray] | None) -> RowArrays | None:
        """Add the episodes from local index ``old`` on (``rows``, or read from disk) to the
        segment's cached copy: the open segment is the newest, so the hottest under recency."""
        entry = self.cache.get(segment.number)
        if entry is None and (old > 0 or self.cache.capacity_bytes == 0):
            return None  # evicted earlier (or no cache): read through the memory maps
        if old < segment.num_episodes:
            rows = rows if rows is not None else segment.load(old)
            if entry is None:
                entry = RowArrays({name: array[:0] for name, array in rows.items()})  # its own copy of the rows
            entry.extend(rows)
        if entry is not None and segment.sealed:
            entry.trim()
        if entry is not None and not self.cache.put(segment.number, entry, entry.nbytes):
            return None
        return entry

    # ------------------------------------------------------------------ writing
    def append(self, episode: Mapping[str, Any], source_id: str | None = None) -> int:
        """Commit one episode (``field -> array``: ``T + 1`` rows per observation field, ``T`` per
        step field); returns its episode id. Raises ``ValueError`` naming a field that does not fit.
        With ``source_id``, an episode of that source id already stored is not appended again: its
        id is returned (:meth:`episode_of_source` tells beforehand)."""
        if not self.writable:
            raise RuntimeError(f"{self.path}: this replay store was opened with writable=False")
        if source_id is not None and self.sources.episode_of(source_id) is not None:
            return self.sources.episode_of(source_id)
        steps, arrays = self.spec.check_episode(episode)
        active = self._active_segment()
        episode_id = self.next_episode_id
        if source_id is not None:
            self.sources.intend(source_id, episode_id)
        try:
            active.append(steps, arrays, episode_id, self.table.end_position, self.options.durable)
        except BaseException:
            if source_id is not None:
                self.sources.forget(source_id)
            raise
        self._index(active, active.num_episodes - 1)
        try:
            if active.data_bytes >= self.options.segment_bytes:
                active.seal(self.options.durable)  # a failed seal leaves the segment open: the next append seals
        finally:
            # The episode is committed even when the seal fails: the cached copy must hold its rows,
            # or the next episode's would be put in their place.
            self._grow_cached(active, active.num_episodes - 1, arrays)
        if active.sealed:
            self._evict()
        return episode_id

    def _active_segment(self) -> Segment:
        if self.segments:
            newest = self.segments[max(self.segments)]
            if not newest.sealed:
                return newest
        number = max(self.segments) + 1 if self.segments else 0
        segment = Segment.create(os.path.join(self.path, "segments", f"{number:08d}"), number, self.spec,
                                 self.options.durable)
        self.segments[number] = segment
        return segment

    def _evict(self) -> None:
        if self.options.max_bytes is None:
            return
        while len(self.segments) > 1 and self.disk_bytes > self.options.max_bytes:
            number = min(self.segments)
            path = self.segments[number].path
            self._forget(number)
            os.replace(path, path + _EVICTING)  # gone from the store in one step, then deleted
            if self.options.durable:
                fsync_directory(os.path.dirname(path))
            shutil.rmtree(path + _EVICTING)

    def _forget(self, number: int) -> None:
        segment = self.segments.pop(number)
        if segment.num_episodes:
            self.table.drop_segment(number)
        self.cache.pop(number)
        segment.close()

    # ------------------------------------------------------------------ reading
    def __len__(self) -> int:
        """Live transitions (those sampling draws from)."""
        return self.table.end_position - self.table.first_live

    def episode_of_source(self, source_id: str) -> int | None:
        """The id of the stored episode appended with ``source_id`` (None when there is none; a
        reader sees those committed when it opened)."""
        return self.sources.episode_of(source_id)

    @property
    def num_episodes(self) -> int:
        return len(self.table)

    @property
    def disk_bytes(self) -> int:
        return sum(s.disk_bytes for s in self.segments.values())

    def sample_positions(self, batch_size: int) -> np.ndarray:
        """Absolute positions of the next mini-batch's transitions (ascending)."""
        return self.sampler.draw(self.table.first_live, self.table.end_position, batch_size)

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        """The next mini-batch: ``obs.<name>``, ``next_obs.<name>`` and every step field (fresh arrays)."""
        return self.gather(self.sample_positions(batch_size))

    def gather(self, positions: np.ndarray) -> dict[str, np.ndarray]:
        """The transitions at sorted absolute ``positions`` (each live)."""
        positions = np.asarray(positions, np.int64)
        if len(positions) and (positions.min() < self.table.first_live or positions.max() >= self.table.end_position):
            raise IndexError(f"replay positions must lie in the live range [{self.table.first_live}, "
                             f"{self.table.end_position}), got [{positions.min()}, {positions.max()}]")
        loc = self.table.locate(positions)
        n = len(positions)
        out = {key: np.empty((n, *shape), dtype) for key, (shape, dtype) in self.spec.batch_fields().items()}
        cuts = np.concatenate([[0], np.flatnonzero(np.diff(loc.segment)) + 1, [n]])
        for a, b in zip(cuts[:-1], cuts[1:]):
            number = int(loc.segment[a])
            arrays = self._arrays(number, loc.local[a:b])
            # mode="clip": the rows are in range by construction, and numpy buffers `out` in mode="raise"
            for name in self.spec.observations:
                np.take(arrays[name], loc.obs_row[a:b], axis=0, out=out[f"obs.{name}"][a:b], mode="clip")
                np.take(arrays[name], loc.obs_row[a:b] + 1, axis=0, out=out[f"next_obs.{name}"][a:b], mode="clip")
            for name in self.spec.steps:
                np.take(arrays[name], loc.step_row[a:b], axis=0, out=out[name][a:b], mode="clip")
        return out

    def _arrays(self, number: int, episodes: np.ndarray) -> dict[str, np.ndarray]:
        cached = self.cache.get(number)
        if cached is not None:
            return cached.view()
        segment = self.segments[number]
        arrays = segment.mapped()
        if self.options.verify_reads:
            segment.verify(np.unique(episodes), arrays)
        return arrays

    def episode(self, episode_id: int) -> dict[str, np.ndarray]:
        """A live episode's fields (copies), checked against its crc32."""
        for segment in self.segments.values():
            local = int(np.searchsorted(segment.episode_ids, episode_id))
            if local < segment.num_episodes and segment.episode_ids[local] == episode_id:
                cached = self.cache.get(segment.number)
                return segment.episode(local, cached.view() if cached is not None else segment.mapped())
        raise KeyError(f"episode {episode_id} is not in the replay store (evicted or never appended)")

    def verify(self) -> None:
        """Check the crc32 of every live episode (reads everything); raises naming the first damaged file."""
        for segment in self.segments.values():
            segment.verified[:] = False
            segment.verify(np.arange(segment.num_episodes), segment.mapped())

    def release_maps(self) -> None:
        """Drop the memory maps of uncached segments (address space; lets ``posix_fadvise`` drop
        their pages); the next read maps them again."""
        for segment in self.segments.values():
            segment.unmap()

    def files(self) -> list[str]:
        """The field files of the live segments."""
        return [segment.file(name) for segment in self.segments.values() for name in segment.names]

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """The sampler's generator and counters, and how many episodes the store held: with the same
        store contents, :meth:`load_state_dict` continues the exact stream of batches."""
        return {"format": FORMAT, "sampler": self.sampler.state_dict(), "episodes": self.next_episode_id}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if state.get("format") != FORMAT:
            raise ValueError(f"replay store state format {state.get('format')}, expected {FORMAT}")
        if self.next_episode_id < int(state["episodes"]):
            raise ValueError(f"{self.path}: the sampler state was taken with {state['episodes']} episodes committed, "
                             f"the store holds {self.next_episode_id}; resume with the store that run wrote")
        self.sampler.load_state_dict(state["sampler"])

    def close(self) -> None:
        for segment in self.segments.values():
            segment.close()
        if self.sources is not None:
            self.sources.close()
        self.cache = ByteLRU(self.options.cache_bytes)
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None

    def __enter__(self) -> ReplayStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
