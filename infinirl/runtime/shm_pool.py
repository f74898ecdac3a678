"""Same-node shared memory for channel items: every process's pool of reusable segments.

A producer copies the CPU tensors of an item into a segment of its pool (``ShmPool.write``) and
sends only a descriptor, a ``ShmItem``: the segment, where each tensor lies in it, and the
payload's structure with the tensors replaced by ``payload.Placeholder``s. A consumer on the same
node maps the segment once (``read`` caches its mappings) and receives tensors that are views of
it: no copy, and writable (each channel item reaches one consumer, which may modify it in place).

Segments are anonymous memory files (``memfd_create``) that the producer holds open; a consumer
opens one as ``/proc/<producer pid>/fd/<fd>`` and checks its inode. Nothing is named in /dev/shm,
so nothing can be left behind there: the kernel frees a segment once its producer has closed it or
exited, however it exited (a worker rank is killed outright, and no exit handler runs then), and
once no consumer maps it any more. An item not yet read when its producer exits is lost, as an
object-store item is when the process that put it dies; a consumer that had mapped the segment
already keeps reading it.

Reuse. A segment begins with a header: a state byte and a generation number. The producer marks a
segment busy when it writes an item into it; the consumer marks it free again when the last view
of the delivered tensors dies (every tensor of an item is a view of one numpy array whose base is
a ``_Lease``, and the lease's finalizer clears the byte). The producer then reuses it, paying a
copy into pages it has mapped already instead of a new file and its page faults for every item.
The generation, renewed at every write and checked at every read, turns a descriptor that outlived
its item into an error instead of another item's data.

Bounds. A pool holds at most ``cap_bytes`` of segments (``INFINIRL_SHM_POOL_BYTES``, default
``DEFAULT_POOL_BYTES``; 0 turns shared memory off): an item that does not fit returns ``None`` and
goes through the object store instead. A segment whose item is never released stays busy until its
producer exits: an item left in a destroyed channel, or a tensor held by a consumer that died (the
producer cannot tell that such a segment will never come back). Both only take room under the cap.
"""

from __future__ import annotations

import logging
import mmap
import os
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from infinirl.runtime import processes
from infinirl.runtime.errors import ChannelError
from infinirl.runtime.payload import DTYPE_BY_NAME, Placeholder, unbox, walk

__all__ = ["DEFAULT_POOL_BYTES", "HEADER_BYTES", "POOL_BYTES_ENV", "ShmItem", "ShmPool", "ShmTensor",
           "forget_stale_mappings", "mapped_segments", "pool", "read", "size_class"]

logger = logging.getLogger(__name__)

POOL_BYTES_ENV = "INFINIRL_SHM_POOL_BYTES"
DEFAULT_POOL_BYTES = 1 << 30
#: the header: state byte at 0, generation (uint64) at 8; tensors start after it
HEADER_BYTES = 64
_GENERATION = slice(8, 16)
ALIGN = 64  # every tensor starts on a cache line (and on its dtype's alignment)
MIN_SEGMENT_BYTES = 1 << 16
FREE, BUSY, RETIRED = 0, 1, 2
_NAME = "infinirl-shm"  # the memfd's name, as /proc/<pid>/maps shows it (memfd:infinirl-shm)


def size_class(nbytes: int) -> int:
    """Bytes of a new segment that holds ``nbytes``: rounded up to an eighth of the power of two
    below it (at most 12.5% unused) and to whole pages, so that items of similar sizes share
    segments."""
    n = max(int(nbytes), MIN_SEGMENT_BYTES)
    step = max(1 << (n.bit_length() - 4), mmap.PAGESIZE)
    return -(-n // step) * step


@dataclass(kw_only=True)
class ShmTensor:
    """Where one tensor of an item lies in its segment."""

    offset: int
    nbytes: int
    shape: tuple
    dtype: str  # torch dtype by name (payload.DTYPE_BY_NAME)


@dataclass(kw_only=True)
class ShmItem:
    """What a channel envelope carries for an item in shared memory: the producer's segment (by
    pid, fd and inode), the generation of the write, the tensors' places, the payload's structure."""

    pid: int
    start: int  # the producer's start time (processes.start_ticks): a pid names one process
    fd: int
    inode: int
    capacity: int
    generation: int
    tensors: list[ShmTensor]
    structure: Any


class _Segment:
    """One memory file of the producer's pool, mapped for the producer's writes."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.fd = os.memfd_create(_NAME, os.MFD_CLOEXEC)
        try:
            os.ftruncate(self.fd, capacity)
            self.mapping = mmap.mmap(self.fd, capacity)
        except BaseException:
            os.close(self.fd)
            raise
        self.inode = os.fstat(self.fd).st_ino
        self.array = np.frombuffer(self.mapping, dtype=np.uint8)
        self.generation = 0

    @property
    def state(self) -> int:
        return int(self.array[0])

    def claim(self) -> int:
        """Mark busy for a new item; returns the item's generation."""
        self.generation += 1
        self.array[_GENERATION].view(np.uint64)[0] = self.generation
        self.array[0] = BUSY
        return self.generation

    def retire(self) -> None:
        """Close it: consumers that mapped it see RETIRED and drop their mappings (its memory is
        freed once the last of them has)."""
        self.array[0] = RETIRED
        self.array = None
        try:
            self.mapping.close()
        except BufferError:  # a view of it still lives here: the mapping goes when that view does
            pass
        os.close(self.fd)


def _layout(tensors: list[torch.Tensor]) -> tuple[list[ShmTensor], int]:
    """Each tensor's place in a segment, and the bytes the segment needs."""
    specs, offset = [], HEADER_BYTES
    for tensor in tensors:
        nbytes = tensor.numel() * tensor.element_size()
        specs.append(ShmTensor(offset=offset, nbytes=nbytes, shape=tuple(tensor.shape), dtype=str(tensor.dtype)))
        offset += -(-nbytes // ALIGN) * ALIGN
    return specs, offset


def _tensor_view(array: np.ndarray, spec: ShmTensor) -> torch.Tensor:
    """The tensor ``spec`` describes, as a view of ``array`` (a whole segment's bytes)."""
    raw = torch.from_numpy(array[spec.offset:spec.offset + spec.nbytes])
    return raw.view(DTYPE_BY_NAME[spec.dtype]).view(spec.shape)


class ShmPool:
    """The segments this process writes items into (``pool()`` is the process's own)."""

    def __init__(self, cap_bytes: int):
        self.cap_bytes = cap_bytes
        self.pid = os.getpid()
        self.start = processes.start_ticks(self.pid)
        self.segments: list[_Segment] = []
        self.stats = {"writes": 0, "created": 0, "retired": 0, "full": 0}
        self._lock = threading.Lock()
        self._warned_full = False

    @property
    def bytes_held(self) -> int:
        return sum(s.capacity for s in self.segments)

    def write(self, payload: Any) -> ShmItem | None:
        """Copy the tensors of ``payload`` into a free segment; ``None`` when it has no tensor or
        when no segment is free and the cap leaves no room for a new one."""
        tensors: list[torch.Tensor] = []

        def leaf(tensor: torch.Tensor) -> Placeholder:
            tensors.append(tensor)
            return Placeholder(len(tensors) - 1)

        structure = walk(payload, leaf)
        if not tensors:
            return None
        specs, need = _layout(tensors)
        with self._lock:
            segment = self._acquire(need)
            if segment is None:
                return None
            generation = segment.claim()
            self.stats["writes"] += 1
        with torch.no_grad():
            for tensor, spec in zip(tensors, specs):
                _tensor_view(segment.array, spec).copy_(tensor)
        return ShmItem(pid=self.pid, start=self.start, fd=segment.fd, inode=segment.inode,
                       capacity=segment.capacity, generation=generation, tensors=specs, structure=structure)

    def release(self, item: ShmItem) -> None:
        """Take back the segment of an item that no consumer will read (its put failed)."""
        with self._lock:
            for segment in self.segments:
                if segment.inode == item.inode and segment.generation == item.generation:
                    segment.array[0] = FREE

    def close(self) -> None:
        """Retire every segment that is free (busy ones stay: their items may still be read)."""
        with self._lock:
            for segment in [s for s in self.segments if s.state == FREE]:
                self._retire(segment)

    def _acquire(self, need: int) -> _Segment | None:
        """A free segment for ``need`` bytes: a close fit, else a new one within the cap, else any
        free one large enough, else a new one after retiring free ones; None if none of these."""
        segment = self._free_segment(need, largest=2 * need)
        if segment is None and self.bytes_held + size_class(need) <= self.cap_bytes:
            segment = self._create(need)
        if segment is None:
            segment = self._free_segment(need, largest=None)
        if segment is None and size_class(need) <= self.cap_bytes:
            for free in [s for s in self.segments if s.state == FREE]:
                if self.bytes_held + size_class(need) <= self.cap_bytes:
                    break
                self._retire(free)
            if self.bytes_held + size_class(need) <= self.cap_bytes:
                segment = self._create(need)
        if segment is None:
            self._note_full(need)
        return segment

    def _free_segment(self, need: int, largest: int | None) -> _Segment | None:
        fits = [s for s in self.segments if s.state == FREE and need <= s.capacity
                and (largest is None or s.capacity <= largest)]
        return min(fits, key=lambda s: s.capacity) if fits else None

    def _create(self, need: int) -> _Segment:
        segment = _Segment(size_class(need))
        self.segments.append(segment)
        self.stats["created"] += 1
        return segment

    def _retire(self, segment: _Segment) -> None:
        self.segments.remove(segment)
        segment.retire()
        self.stats["retired"] += 1

    def _note_full(self, need: int) -> None:
        self.stats["full"] += 1
        if not self._warned_full:
            self._warned_full = True
            logger.warning(
                "shared-memory pool of pid %d is full (%d of %d bytes busy, an item needs %d): such items go "
                "through Ray's object store until consumers release theirs; raise %s to keep them in shared "
                "memory", self.pid, self.bytes_held, self.cap_bytes, need, POOL_BYTES_ENV)


_pool: ShmPool | None = None
_pool_lock = threading.Lock()


def pool() -> ShmPool:
    """This process's pool (a forked child gets its own)."""
    global _pool
    with _pool_lock:
        if _pool is None or _pool.pid != os.getpid():
            _pool = ShmPool(cap_bytes=_cap_from_env())
        return _pool


def _cap_from_env() -> int:
    if not hasattr(os, "memfd_create"):
        return 0
    value = os.environ.get(POOL_BYTES_ENV, "")
    try:
        cap = int(value) if value.strip() else DEFAULT_POOL_BYTES
    except ValueError:
        raise ValueError(f"{POOL_BYTES_ENV}={value!r} is not a number of bytes; set it to e.g. "
                         f"{DEFAULT_POOL_BYTES}, or 0 to send channel items through the object store") from None
    return max(cap, 0)


# ---------------------------------------------------------------------------------------- consumer
class _Mapping:
    """A consumer's mapping of one producer segment (kept while the producer lives and uses it)."""

    __slots__ = ("pid", "start", "capacity", "mapping", "array", "address")

    def __init__(self, item: ShmItem):
        path = f"/proc/{item.pid}/fd/{item.fd}"
        try:
            fd = os.open(path, os.O_RDWR)
        except FileNotFoundError:
            raise ChannelError(f"a channel item in shared memory of pid {item.pid} cannot be read: that process "
                               "exited (or retired the segment) before the item was read") from None
        except PermissionError as exc:
            raise ChannelError(f"a channel item in shared memory of pid {item.pid} cannot be read: {exc}. This "
                               f"process may not open another's /proc/<pid>/fd; set {POOL_BYTES_ENV}=0 for every "
                               "process to send items through Ray's object store") from None
        try:
            if os.fstat(fd).st_ino != item.inode:
                raise ChannelError(f"a channel item in shared memory of pid {item.pid} cannot be read: its segment "
                                   "was closed before the item was read (its fd now names another file)")
            self.mapping = mmap.mmap(fd, item.capacity)
        finally:
            os.close(fd)
        self.pid, self.start, self.capacity = item.pid, item.start, item.capacity
        self.array = np.frombuffer(self.mapping, dtype=np.uint8)
        self.address = self.array.ctypes.data

    def stale(self, alive: dict[int, bool]) -> bool:
        if self.array[0] == RETIRED:
            return True
        if self.pid not in alive:
            alive[self.pid] = processes.alive(self.pid, self.start)
        return not alive[self.pid]


class _Lease:
    """The numpy base of every tensor of one delivered item: when the last of them dies, the
    segment is free again for its producer."""

    def __init__(self, mapped: _Mapping):
        self._mapped = mapped
        self.__array_interface__ = {"data": (mapped.address, False), "shape": (mapped.capacity,),
                                    "typestr": "|u1", "version": 3}

    def __del__(self):
        try:
            self._mapped.array[0] = FREE
        except Exception:  # interpreter shutdown: nothing is left to reuse it
            pass


_mappings: dict[tuple[int, int], _Mapping] = {}  # by (producer pid, inode)
_mappings_lock = threading.Lock()


def read(item: ShmItem) -> Any:
    """The payload of ``item``: its tensors are writable views of the producer's segment, which is
    free for reuse once the last of them is gone."""
    mapped = _mapped(item)
    generation = int(mapped.array[_GENERATION].view(np.uint64)[0])
    if mapped.array[0] != BUSY or generation != item.generation:
        raise ChannelError(f"a channel item in shared memory of pid {item.pid} was overwritten before it was read "
                           f"(generation {generation}, expected {item.generation}): a routing bug")
    base = np.asarray(_Lease(mapped))
    return unbox(item.structure, leaf=lambda placeholder: _tensor_view(base, item.tensors[placeholder.index]))


def _mapped(item: ShmItem) -> _Mapping:
    key = (item.pid, item.inode)
    with _mappings_lock:
        mapped = _mappings.get(key)
        if mapped is None:
            _forget_stale_locked()
            mapped = _mappings[key] = _Mapping(item)
        return mapped


def forget_stale_mappings() -> int:
    """Drop this process's mappings of segments whose producer retired them or exited (each one's
    memory goes once the tensors still viewing it do). Runs by itself whenever a new segment is
    mapped; returns how many were dropped."""
    with _mappings_lock:
        return _forget_stale_locked()


def _forget_stale_locked() -> int:
    alive: dict[int, bool] = {}
    stale = [key for key, mapped in _mappings.items() if mapped.stale(alive)]
    for key in stale:
        del _mappings[key]
    return len(stale)


def mapped_segments() -> list[tuple[int, int]]:
    """(producer pid, inode) of every segment this process keeps mapped for reading."""
    with _mappings_lock:
        return sorted(_mappings)
