"""Channel: a named, keyed, weighted, bounded queue between worker groups.

The queue lives in a small async Ray actor and holds *metadata only* (an ``Envelope``: path,
producer, weight, and a ref or a small inline payload). Payloads move from producer to consumer by
the cheapest path (see ``transport``): never twice through a channel actor, as RLinf's do.

- ``put(item, key=, weight=)`` blocks while the channel is full (``maxsize`` is a capacity in
  *weight* units; weight defaults to 1, so by default it counts items): back-pressure.
- ``get(key=)`` takes the oldest item of a key (per-key FIFO).
- ``get_batch(target_weight, key=)`` takes items until their weights reach the target: consumers
  asking for equal weight get balanced work even when items differ in size (e.g. token counts).
- ``close()``: producers are done. Getters drain what is left, then get ``ChannelClosed``.
- Every call has an ``*_async`` twin for use inside ``async def`` worker methods.

A ``Channel`` object is picklable: pass it to worker methods, or ``Channel.connect(name)`` anywhere.
"""

from __future__ import annotations

import asyncio
import os
import time
import uuid
from collections import deque
from typing import Any

import ray

from infinirl.runtime.cluster import NAMESPACE
from infinirl.runtime.errors import ChannelClosed, ChannelError
from infinirl.runtime.transport import Envelope, pack, unpack

DEFAULT_KEY = "default"
_ACTOR_PREFIX = "infinirl.channel."


class _Item:
    __slots__ = ("envelope", "weight", "pinned_pid")

    def __init__(self, envelope: Envelope, weight: float, pinned_pid: int | None):
        self.envelope = envelope
        self.weight = weight
        self.pinned_pid = pinned_pid


class _ChannelActor:
    """Holds per-key deques of envelopes; all waiting happens here, on asyncio conditions."""

    def __init__(self, name: str, maxsize: float, transport: str = "auto", pipeline_depth: int = 0,
                 prefetch: int = 1):
        self.name = name
        self.transport = transport
        self.pipeline_depth = pipeline_depth
        self.prefetch = prefetch
        self.next_seq: dict[str, int] = {}
        self.maxsize = maxsize
        self.queues: dict[Any, deque[_Item]] = {}
        self.weight_in_queue = 0.0
        self.closed = False
        self.cond = asyncio.Condition()
        self.consumer_pids: set[int] = set()
        self.stats = {"put": 0, "get": 0}

    async def put(self, envelope: Envelope, key, weight: float, timeout: float | None,
                  producer: str | None = None, seq: int = -1):
        if seq < 0:
            return await self._put(envelope, key, weight, timeout)
        # Pipelined producers number their puts: Ray does not promise that an async actor starts
        # calls in submission order, and per-producer FIFO must hold.
        async with self.cond:
            await self.cond.wait_for(lambda: self.next_seq.get(producer, 0) == seq)
        try:
            return await self._put(envelope, key, weight, timeout)
        finally:
            async with self.cond:
                self.next_seq[producer] = seq + 1
                self.cond.notify_all()

    async def _put(self, envelope: Envelope, key, weight: float, timeout: float | None):
        if self.closed:
            raise ChannelClosed(f"put on closed channel '{self.name}'")
        if self.maxsize and weight > self.maxsize:
            raise ChannelError(
                f"channel '{self.name}': an item of weight {weight} can never fit maxsize={self.maxsize}; "
                "raise maxsize or split the item"
            )
        pinned = envelope.producer_pid if envelope.path == "local" else None
        async with self.cond:
            if self.maxsize:
                await self._wait_for(lambda: self.weight_in_queue + weight <= self.maxsize or self.closed, timeout, "put")
                if self.closed:
                    raise ChannelClosed(f"channel '{self.name}' closed while a put waited for space")
            self.queues.setdefault(key, deque()).append(_Item(envelope, weight, pinned))
            self.weight_in_queue += weight
            self.stats["put"] += 1
            self.cond.notify_all()
        return sorted(self.consumer_pids)

    async def put_many(self, envelopes: list[Envelope], key, weights: list[float], timeout):
        for envelope, weight in zip(envelopes, weights):
            await self.put(envelope, key, weight, timeout)
        return sorted(self.consumer_pids)

    def _eligible(self, key, pid: int) -> int | None:
        queue = self.queues.get(key)
        if not queue:
            return None
        for index, item in enumerate(queue):
            if item.pinned_pid is None or item.pinned_pid == pid:
                return index
        return None

    def _take(self, key, index: int) -> _Item:
        queue = self.queues[key]
        if index == 0:
            item = queue.popleft()
        else:
            item = queue[index]
            del queue[index]
        self.weight_in_queue -= item.weight
        self.stats["get"] += 1
        return item

    async def get(self, key, pid: int, timeout: float | None):
        self.consumer_pids.add(pid)
        async with self.cond:
            await self._wait_for(lambda: self._eligible(key, pid) is not None or self.closed, timeout, "get")
            index = self._eligible(key, pid)
            if index is None:
                raise ChannelClosed(f"channel '{self.name}' is closed and has no more items for key {key!r}")
            item = self._take(key, index)
            self.cond.notify_all()
            return item.envelope, item.weight

    async def get_many(self, key, pid: int, max_items: int, timeout: float | None):
        """Wait for one item, then also take up to ``max_items - 1`` more already waiting (prefetch)."""
        self.consumer_pids.add(pid)
        async with self.cond:
            await self._wait_for(lambda: self._eligible(key, pid) is not None or self.closed, timeout, "get")
            taken = []
            while len(taken) < max_items:
                index = self._eligible(key, pid)
                if index is None:
                    break
                item = self._take(key, index)
                taken.append((item.envelope, item.weight))
            if not taken:
                raise ChannelClosed(f"channel '{self.name}' is closed and has no more items for key {key!r}")
            self.cond.notify_all()
            return taken

    async def get_batch(self, target_weight: float, key, pid: int, timeout: float | None):
        self.consumer_pids.add(pid)
        taken: list[tuple[Envelope, float]] = []
        total = 0.0
        async with self.cond:
            while total < target_weight:
                try:
                    await self._wait_for(
                        lambda: self._eligible(key, pid) is not None or self.closed, timeout, "get_batch"
                    )
                except TimeoutError:
                    if taken:
                        break
                    raise
                index = self._eligible(key, pid)
                if index is None:  # closed and drained
                    if taken:
                        break
                    raise ChannelClosed(f"channel '{self.name}' is closed and has no more items for key {key!r}")
                item = self._take(key, index)
                taken.append((item.envelope, item.weight))
                total += item.weight
                self.cond.notify_all()
        return taken

    async def register_consumer(self, pid: int) -> None:
        self.consumer_pids.add(pid)

    async def close(self) -> None:
        async with self.cond:
            self.closed = True
            self.cond.notify_all()

    async def qsize(self, key=None) -> int:
        if key is None:
            return sum(len(q) for q in self.queues.values())
        return len(self.queues.get(key, ()))

    async def info(self) -> dict:
        return {"name": self.name, "maxsize": self.maxsize, "closed": self.closed, "transport": self.transport,
                "pipeline_depth": self.pipeline_depth, "prefetch": self.prefetch,
                "weight_in_queue": self.weight_in_queue, **self.stats}

    async def _wait_for(self, predicate, timeout: float | None, op: str) -> None:
        try:
            await asyncio.wait_for(self.cond.wait_for(predicate), timeout)
        except asyncio.TimeoutError:
            raise TimeoutError(f"channel '{self.name}': {op} timed out after {timeout}s") from None


class Channel:
    """Client handle on a named channel; cheap to pickle and send to workers."""

    def __init__(self, name: str, actor, transport: str = "auto", pipeline_depth: int = 0, prefetch: int = 1):
        self.name = name
        self._actor = actor
        self.transport = transport
        self.pipeline_depth = pipeline_depth
        self.prefetch = prefetch
        self._prefetched: dict[Any, deque] = {}
        self._consumers_here_only = False
        self._producer = uuid.uuid4().hex  # per client: a pickled copy in a worker is a new producer
        self._seq = 0
        self._inflight: deque = deque()

    # ------------------------------------------------------------------ create / connect
    @classmethod
    def create(cls, name: str, maxsize: float = 0, exist_ok: bool = False, transport: str = "auto",
               pipeline_depth: int = 0, prefetch: int = 1) -> "Channel":
        """Create the channel ``name`` (``maxsize`` 0 = unbounded). Call from the driver or a worker.

        ``transport``: ``"auto"`` picks the cheapest path per item (see ``transport``); ``"p2p"``
        sends tensors producer -> consumer over a pairwise gloo/NCCL group (useful across nodes
        or GPUs; producers must be Workers, the driver falls back to the object store).

        ``pipeline_depth`` > 0 lets a streaming producer keep that many ``put`` calls in flight
        instead of waiting for each acknowledgement: per-producer order is kept, back-pressure
        still holds (a producer runs at most ``pipeline_depth`` items ahead of ``maxsize``), and
        errors such as a closed channel surface on a later ``put``, ``flush()`` or ``close()``.

        ``prefetch`` > 1 lets ``get`` take up to that many waiting items in one round trip and hand
        them out one by one (a consumer then holds at most ``prefetch - 1`` items others cannot
        take). Both options trade a little strictness for throughput on streaming stages.
        """
        if prefetch < 1:
            raise ChannelError(f"channel '{name}': prefetch must be >= 1, got {prefetch}")
        if pipeline_depth < 0:
            raise ChannelError(f"channel '{name}': pipeline_depth must be >= 0, got {pipeline_depth}")
        if transport not in ("auto", "p2p"):
            raise ChannelError(f"channel '{name}': transport={transport!r}; use 'auto' or 'p2p'")
        if maxsize < 0:
            raise ChannelError(f"channel '{name}': maxsize must be >= 0 (0 = unbounded), got {maxsize}")
        actor_cls = ray.remote(_ChannelActor).options(
            name=_ACTOR_PREFIX + name,
            namespace=NAMESPACE,
            num_cpus=0,
            max_concurrency=10_000,
            get_if_exists=exist_ok,
        )
        try:
            actor = actor_cls.remote(name, maxsize, transport, pipeline_depth, prefetch)
        except ValueError as exc:
            raise ChannelError(
                f"a channel named '{name}' already exists; use Channel.connect('{name}') or exist_ok=True"
            ) from exc
        return cls(name, actor, transport, pipeline_depth, prefetch)

    @classmethod
    def connect(cls, name: str, timeout_s: float = 30.0) -> "Channel":
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                actor = ray.get_actor(_ACTOR_PREFIX + name, namespace=NAMESPACE)
                info = ray.get(actor.info.remote())
                return cls(name, actor, info["transport"], info["pipeline_depth"], info["prefetch"])
            except ValueError:
                if time.monotonic() > deadline:
                    raise ChannelError(
                        f"no channel named '{name}' after {timeout_s}s; create it with Channel.create('{name}')"
                    ) from None
                time.sleep(0.1)

    def __reduce__(self):
        return (Channel, (self.name, self._actor, self.transport, self.pipeline_depth, self.prefetch))

    # ------------------------------------------------------------------ sync API
    def put(self, item: Any, key=DEFAULT_KEY, weight: float = 1.0, timeout: float | None = None) -> None:
        if not self.pipeline_depth:
            self._note_consumers(self._call(self._actor.put.remote(self._pack(item), key, float(weight), timeout)))
            return
        self._inflight.append(
            self._actor.put.remote(self._pack(item), key, float(weight), timeout, self._producer, self._seq)
        )
        self._seq += 1
        while len(self._inflight) > self.pipeline_depth:
            self._note_consumers(self._call(self._inflight.popleft()))

    def flush(self) -> None:
        """Wait until every pipelined ``put`` of this client has been accepted (raises its error)."""
        while self._inflight:
            self._note_consumers(self._call(self._inflight.popleft()))

    def put_many(self, items: list, key=DEFAULT_KEY, weights: list[float] | None = None, timeout=None) -> None:
        """Put several items with one round trip (they stay in order)."""
        weights = [1.0] * len(items) if weights is None else [float(w) for w in weights]
        consumers = self._call(self._actor.put_many.remote([self._pack(i) for i in items], key, weights, timeout))
        self._note_consumers(consumers)

    def get(self, key=DEFAULT_KEY, timeout: float | None = None) -> Any:
        if self.prefetch > 1:
            buffered = self._prefetched.setdefault(key, deque())
            if not buffered:
                buffered.extend(self._call(self._actor.get_many.remote(key, os.getpid(), self.prefetch, timeout)))
            envelope, _ = buffered.popleft()
            return unpack(envelope)
        envelope, _ = self._call(self._actor.get.remote(key, os.getpid(), timeout))
        return unpack(envelope)

    def get_with_weight(self, key=DEFAULT_KEY, timeout: float | None = None) -> tuple[Any, float]:
        envelope, weight = self._call(self._actor.get.remote(key, os.getpid(), timeout))
        return unpack(envelope), weight

    def get_batch(self, target_weight: float, key=DEFAULT_KEY, timeout: float | None = None) -> list:
        """Items until their total weight reaches ``target_weight`` (fewer if the channel closes)."""
        taken = self._call(self._actor.get_batch.remote(float(target_weight), key, os.getpid(), timeout))
        return [unpack(envelope) for envelope, _ in taken]

    def close(self) -> None:
        self.flush()
        ray.get(self._actor.close.remote())

    def qsize(self, key=None) -> int:
        return ray.get(self._actor.qsize.remote(key))

    def info(self) -> dict:
        return ray.get(self._actor.info.remote())

    def register_consumer(self) -> None:
        """Declare this process a consumer (lets same-process producers hand items by reference)."""
        ray.get(self._actor.register_consumer.remote(os.getpid()))

    def destroy(self) -> None:
        ray.kill(self._actor)

    # ------------------------------------------------------------------ async API
    async def put_async(self, item: Any, key=DEFAULT_KEY, weight: float = 1.0, timeout=None) -> None:
        self._note_consumers(await self._acall(self._actor.put.remote(self._pack(item), key, float(weight), timeout)))

    async def get_async(self, key=DEFAULT_KEY, timeout: float | None = None) -> Any:
        envelope, _ = await self._acall(self._actor.get.remote(key, os.getpid(), timeout))
        return unpack(envelope)

    async def get_batch_async(self, target_weight: float, key=DEFAULT_KEY, timeout=None) -> list:
        taken = await self._acall(self._actor.get_batch.remote(float(target_weight), key, os.getpid(), timeout))
        return [unpack(envelope) for envelope, _ in taken]

    # ------------------------------------------------------------------ internals
    def _pack(self, item: Any) -> Envelope:
        return pack(item, same_process=self._consumers_here_only, force_p2p=self.transport == "p2p")

    def _note_consumers(self, consumer_pids: list[int]) -> None:
        # By-reference hand-over is only safe when every consumer seen so far is this process.
        self._consumers_here_only = bool(consumer_pids) and set(consumer_pids) == {os.getpid()}

    @staticmethod
    def _call(ref):
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            raise _unwrap(exc) from None

    @staticmethod
    async def _acall(ref):
        try:
            return await ref
        except ray.exceptions.RayTaskError as exc:
            raise _unwrap(exc) from None


def _unwrap(exc: ray.exceptions.RayTaskError) -> BaseException:
    cause = getattr(exc, "cause", None)
    if isinstance(cause, (ChannelClosed, ChannelError, TimeoutError)):
        return cause
    return exc
