"""Channel: a named, keyed, weighted, bounded queue between worker groups.

The queue lives in a small async Ray actor (``channel_actor``) and holds *metadata only* (an
``Envelope``: path, producer, weight, and a ref, a shared-memory descriptor or a small inline
payload). Payloads move from producer to consumer by the cheapest path (see ``transport``), never
through the channel actor: a producer picks shared memory while every consumer the channel knows
runs on its node, which the replies to its registration and puts tell it.

- ``put(item, key=, weight=)`` blocks while the item's key is full: ``maxsize`` is a capacity
  *per key*, in weight units (weight defaults to 1, so by default it counts items). Keys never
  block each other: a consumer reading one key while another key fills up cannot deadlock.
- ``get(key=)`` takes the oldest item of a key (per-key FIFO).
- ``get_batch(target_weight, key=)`` takes items in order while their total weight stays within
  the target: consumers asking for equal weight get balanced work even when items differ in
  size (e.g. token counts). An item heavier than the target comes alone.
- ``close()``: producers are done. Getters drain what is left, then get ``ChannelClosed``.
- A producer or consumer that dies cannot leave the other side waiting forever: once every
  producer of the channel has died, a getter that finds no item gets ``ChannelPeerDied``; once
  every consumer has died, so does a putter waiting for space (see ``channel_actor``).
- A prefetching consumer (``prefetch`` > 1) holds the items it took ahead under a lease of the
  channel actor: if its process dies before handing them out, they go back to the front of their
  queue for the others, and the channel logs it (see ``channel_actor``).
- Waits have no default timeout (a consumer may wait for a long rollout); ``timeout=`` bounds one
  call, and a synchronous wait inside a worker method ends with ``CallCancelled`` when that
  method's call is cancelled (``GroupHandle.cancel()``).
- Every call has an ``*_async`` twin for use inside ``async def`` worker methods.

A ``Channel`` object is picklable: pass it to worker methods, or ``Channel.connect(name)`` anywhere.
"""

from __future__ import annotations

import asyncio
import math
import os
import threading
import time
import uuid
from collections import deque
from typing import Any

import ray

from infinirl.runtime import cancellation, p2p, processes
from infinirl.runtime.channel_actor import ChannelActor
from infinirl.runtime.errors import CallCancelled, ChannelClosed, ChannelError
from infinirl.runtime.payload import tensor_bytes, unbox
from infinirl.runtime.ray_defaults import NAMESPACE
from infinirl.runtime.transport import (
    INLINE_LIMIT_BYTES,
    Envelope,
    discard,
    pack,
    shared_memory_reaches,
    unpack,
)

DEFAULT_KEY = "default"
_ACTOR_PREFIX = "infinirl.channel."
# An abandoned get ends at once; this only bounds the wait if its actor is stuck or gone.
ABANDON_WAIT_S = 60.0
# A cancelled synchronous get is abandoned from the host's event loop, inside the cancelled call,
# and Ray cancels the calls a cancelled call makes: that abandon can be cancelled before it runs.
# So the waiting thread abandons the get again once it sees the cancel (cancellation.wait_ref), and
# then waits at most CANCELLED_GET_WAIT_S for the reply, which Ray can also lose.
CANCELLED_GET_WAIT_S = cancellation.CANCELLED_WAIT_S


class Channel:
    """Client handle on a named channel; cheap to pickle and send to workers."""

    def __init__(self, name: str, actor, transport: str = "auto", pipeline_depth: int = 0, prefetch: int = 1):
        self.name = name
        self._actor = actor
        self.transport = transport
        self.pipeline_depth = pipeline_depth
        self.prefetch = prefetch
        self._prefetched: dict[Any, deque] = {}  # by key; a key is dropped once its buffer is empty
        self._leases: dict[Any, str] = {}  # key -> the get whose items its buffer holds (leased to this process)
        self._handed_out: list[str] = []  # leases whose items were all handed out: said with the next get_many
        self._consumers_here_only = False
        self._consumers_on_this_node = False
        self._consumers_known = False  # a reply of the channel said who the consumers are
        self._registration = None  # the producer registration's reply, until it is read
        self._producer = uuid.uuid4().hex  # per client: a pickled copy in a worker is a new producer
        self._seq = 0
        # Threads sharing this client take put numbers under it: two with the same number would
        # leave a later one unused, and the channel would hold every put behind it for good.
        self._seq_lock = threading.Lock()
        self._inflight: deque = deque()
        self._roles: set[str] = set()  # registered with the channel actor from this client

    # ------------------------------------------------------------------ create / connect
    @classmethod
    def create(cls, name: str, maxsize: float = 0, exist_ok: bool = False, transport: str = "auto",
               pipeline_depth: int = 0, prefetch: int = 1) -> "Channel":
        """Create the channel ``name``. Call from the driver or a worker.

        ``exist_ok``: return the channel if it exists already; one that exists with another
        ``maxsize`` or ``transport`` is refused (``ChannelError``).

        ``maxsize``: the capacity of *each key*, in weight units (0 = unbounded). A put waits
        while its key's queued weight plus the item's would exceed it; an item heavier than
        ``maxsize`` is refused at once.

        ``transport``: ``"auto"`` picks the cheapest path per item (see ``transport``); ``"p2p"``
        sends tensors producer -> consumer over a pairwise gloo/NCCL group (useful across nodes
        or GPUs; producers must be Workers, the driver falls back to the object store).

        ``pipeline_depth`` > 0 lets a streaming producer keep that many ``put`` calls in flight
        instead of waiting for each acknowledgement: per-producer order is kept (``put_many`` and
        ``put_async`` of the same client queue behind the puts still in flight), back-pressure
        still holds (a producer runs at most ``pipeline_depth`` items ahead of ``maxsize``), and
        errors such as a closed channel surface on a later ``put``, ``flush()`` or ``close()``.

        ``prefetch`` > 1 lets ``get`` take up to that many waiting items in one round trip and hand
        them out one by one (a consumer then holds at most ``prefetch - 1`` items others cannot
        take; its other gets serve those first, or, for a batch, give them back first, so a key's
        order holds). If its process dies, the items it held go back to the queue, and so may the ones it
        handed out since its last round trip (delivered again, to another consumer). Both options
        trade a little strictness for throughput on streaming stages.
        """
        if prefetch < 1:
            raise ChannelError(f"channel '{name}': prefetch must be >= 1, got {prefetch}")
        if pipeline_depth < 0:
            raise ChannelError(f"channel '{name}': pipeline_depth must be >= 0, got {pipeline_depth}")
        if transport not in ("auto", "p2p"):
            raise ChannelError(f"channel '{name}': transport={transport!r}; use 'auto' or 'p2p'")
        if not maxsize >= 0:
            raise ChannelError(f"channel '{name}': maxsize must be >= 0 (0 = unbounded), got {maxsize}")
        actor_cls = ray.remote(ChannelActor).options(
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
        if exist_ok:  # it may be another creator's: its queue must be the one asked for
            info = ray.get(actor.info.remote())
            for setting, wanted in (("maxsize", maxsize), ("transport", transport)):
                if info[setting] != wanted:
                    raise ChannelError(
                        f"channel '{name}': Channel.create(exist_ok=True) asked for {setting}={wanted!r}, but the "
                        f"channel exists with {setting}={info[setting]!r}; create it with the same {setting} "
                        f"everywhere, or use Channel.connect('{name}')")
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
        """Queue ``item`` under ``key``; waits while the key is full (``timeout``: at most that long).

        The item is handed over: do not change its tensors afterwards. A consumer in this process,
        a p2p pull and a CUDA IPC handle get this very memory, so refilling one buffer and putting
        it again can deliver later data; put a copy (``buf.clone()``) of a buffer that is reused."""
        weight = self._check_weight(weight, "weight")
        self._register("producer")
        envelope = self._pack(item)
        if not self.pipeline_depth:
            self._settle_put(self._actor.put.remote(envelope, key, weight, timeout), envelope)
            return
        with self._seq_lock:
            self._inflight.append((self._submit_put(self._actor.put, envelope, key, weight, timeout), envelope))
        while len(self._inflight) > self.pipeline_depth:
            if not self._settle_next():
                break

    def flush(self) -> None:
        """Wait until every pipelined ``put`` of this client has been accepted (raises its error)."""
        while self._settle_next():
            pass

    def _submit_put(self, method, *args):
        """Submit a put (or put_many) call; with ``pipeline_depth`` it takes the next number of this
        producer's order, so that it lands behind the pipelined puts still in flight. Called under
        ``_seq_lock`` where the call is pipelined."""
        if not self.pipeline_depth:
            return method.remote(*args)
        ref = method.remote(*args, self._producer, self._seq)
        self._seq += 1
        return ref

    def _settle_next(self) -> bool:
        """Settle the oldest put in flight; False if none is (another thread took the last one)."""
        try:
            ref, envelope = self._inflight.popleft()
        except IndexError:
            return False
        self._settle_put(ref, envelope)
        return True

    def put_many(self, items: list, key=DEFAULT_KEY, weights: list[float] | None = None, timeout=None) -> None:
        """Put several items with one round trip (they stay in order)."""
        if weights is None:
            weights = [1.0] * len(items)
        elif len(weights) != len(items):
            raise ValueError(f"channel '{self.name}': put_many got {len(items)} items but {len(weights)} weights")
        weights = [self._check_weight(w, "weights") for w in weights]
        self._register("producer")
        # On a failure, some of the items may be queued already: none is discarded (a segment
        # of this process's shared memory stays busy until the process exits, within its cap).
        envelopes = [self._pack(i) for i in items]
        with self._seq_lock:  # numbered like a pipelined put: queued behind those in flight
            ref = self._submit_put(self._actor.put_many, envelopes, key, weights, timeout)
        consumers = self._call(ref)
        self._note_consumers(consumers)

    def get(self, key=DEFAULT_KEY, timeout: float | None = None) -> Any:
        """The oldest item of ``key``; waits for one (``timeout``: at most that many seconds)."""
        self._register("consumer")
        if self.prefetch > 1:
            return self._get_prefetched(key, timeout)[0]
        envelope, _ = self._get(self._actor.get, key, os.getpid(), _peer_id(), timeout)
        return unpack(envelope)

    def _get_prefetched(self, key, timeout: float | None) -> tuple[Any, float]:
        """``get`` with ``prefetch`` > 1, as ``(item, weight)``: from this client's buffer of
        ``key``, refilled by one ``get_many``. That call also tells the channel which of this client's
        leases are handed out in full: the acknowledgement costs no message of its own."""
        buffered = self._prefetched.get(key)
        if not buffered:
            request = uuid.uuid4().hex
            taken = self._get(self._actor.get_many, key, os.getpid(), _peer_id(), self.prefetch, timeout,
                              request=request, handed_out=self._handed_out)
            self._handed_out = []  # only once the call succeeded: settling a lease twice is harmless
            if len(taken) > 1:  # the channel leased the items beyond the first to this process
                self._leases[key] = request
            try:
                buffered = self._prefetched[key] = deque(_prefetch_entries(taken))
            except BaseException:  # nothing buffered: the lease has nothing left to hand out
                self._settle(key)
                raise
        envelope, weight, value = buffered.popleft()
        if not buffered:
            self._settle(key)
        return (unpack(envelope) if value is _UNREAD else value), weight

    def _settle(self, key) -> None:
        """The buffer of ``key`` is empty: its lease is to be settled with the next get_many."""
        self._prefetched.pop(key, None)
        lease = self._leases.pop(key, None)
        if lease is not None:
            self._handed_out.append(lease)

    def get_with_weight(self, key=DEFAULT_KEY, timeout: float | None = None) -> tuple[Any, float]:
        self._register("consumer")
        if self.prefetch > 1:
            return self._get_prefetched(key, timeout)
        envelope, weight = self._get(self._actor.get, key, os.getpid(), _peer_id(), timeout)
        return unpack(envelope), weight

    def get_batch(self, target_weight: float, key=DEFAULT_KEY, timeout: float | None = None) -> list:
        """Items of ``key``, oldest first, whose total weight stays within ``target_weight``.

        Returns once the total equals the target or the next item would exceed it; an item heavier
        than the target is returned alone. Returns short (whatever it has, if anything) when the
        channel is closed and drained, when every producer has died, or when ``timeout`` expires;
        with nothing to return it raises ``ChannelClosed``, ``ChannelPeerDied`` or ``TimeoutError``.
        """
        target = self._check_target(target_weight)
        self._register("consumer")
        if key in self._prefetched:  # older than what the channel holds: they go back first, in order
            self._give_back_buffered(key)
        taken = self._get(self._actor.get_batch, target, key, os.getpid(), _peer_id(), timeout, key=key)
        return self._unpack_batch(key, taken)

    def give_back_prefetched(self) -> int:
        """Return the items ``get`` prefetched but did not hand out yet to the front of their
        queues, for other consumers; a consumer that stops getting before the channel ends calls
        this so that nothing stays stranded in it (it also tells the channel that the items it
        handed out are handed out, so that its process's exit later re-queues none of them).
        Returns how many items went back."""
        returned = sum(self._give_back_buffered(key) for key in list(self._prefetched))
        if self._handed_out:
            self._call(self._actor.settle_leases.remote(self._handed_out))
            self._handed_out = []
        return returned

    def _give_back_buffered(self, key) -> int:
        """Return the buffer of ``key`` to the front of its queue, ending its lease."""
        return self._call(self._give_back_buffered_ref(key))

    def _give_back_buffered_ref(self, key):
        buffered = self._prefetched.pop(key)
        return self._actor.give_back.remote(key, [(e, w) for e, w, _ in buffered], self._leases.pop(key, None))

    def close(self) -> None:
        self.flush()
        self._call(self._actor.close.remote())

    def qsize(self, key=None) -> int:
        return self._call(self._actor.qsize.remote(key))

    def info(self) -> dict:
        return self._call(self._actor.info.remote())

    def register_consumer(self) -> None:
        """Declare this process a consumer before its first get: same-process producers may then
        hand items over by reference, and producers waiting for space learn if it dies."""
        self._register("consumer")
        self._call(self._actor.register_consumer.remote(os.getpid(), _node_id()))

    def register_producer(self) -> None:
        """Declare this process a producer before its first put, so that consumers waiting on
        the channel learn if it dies before it has put anything."""
        self._register("producer", wait=True)

    def destroy(self) -> None:
        """End the channel for everyone (its actor). The queued items this process put that live in
        its memory (same-process items, p2p tensors, shared-memory segments) are dropped first;
        another producer process keeps its own until it exits."""
        try:
            queued = ray.get(self._actor.queued.remote(), timeout=ABANDON_WAIT_S)
        except Exception:  # the actor is gone already: nothing to ask
            queued = []
        for envelope in queued:
            if envelope.producer_pid == os.getpid() and envelope.producer_node == _node_id():
                discard(envelope)
        ray.kill(self._actor)

    # ------------------------------------------------------------------ async API
    async def put_async(self, item: Any, key=DEFAULT_KEY, weight: float = 1.0, timeout=None) -> None:
        weight = self._check_weight(weight, "weight")
        self._register("producer")
        if self._registration is not None and not self._consumers_known and tensor_bytes(item) >= INLINE_LIMIT_BYTES:
            registration, self._registration = self._registration, None  # awaited here, not blocking the loop
            self._note_consumers(await self._acall(registration))
        envelope = self._pack(item)
        try:
            with self._seq_lock:  # numbered like a pipelined put: queued behind those in flight
                ref = self._submit_put(self._actor.put, envelope, key, weight, timeout)
            self._note_consumers(await self._acall(ref))
        except Exception:  # refused, or its actor is gone: the item is not queued (a cancel may have queued it)
            discard(envelope)
            raise

    async def get_async(self, key=DEFAULT_KEY, timeout: float | None = None) -> Any:
        self._register("consumer")
        buffered = self._prefetched.get(key)
        if buffered:  # items a prefetching get took ahead come first
            envelope, _, value = buffered.popleft()
            if not buffered:
                self._settle(key)
            if value is not _UNREAD:
                return value
        else:
            envelope, _ = await self._aget(self._actor.get, key, os.getpid(), _peer_id(), timeout)
        # Off the event loop: a p2p pull waits for its producer, which may wait on this loop to serve one
        return await asyncio.get_running_loop().run_in_executor(p2p.PULLS, unpack, envelope)

    async def get_batch_async(self, target_weight: float, key=DEFAULT_KEY, timeout=None) -> list:
        target = self._check_target(target_weight)
        self._register("consumer")
        if key in self._prefetched:  # as in get_batch
            await self._acall(self._give_back_buffered_ref(key))
        taken = await self._aget(self._actor.get_batch, target, key, os.getpid(), _peer_id(), timeout, key=key)
        # Off the event loop for the same reason as get_async (and ray.get must not block a running loop)
        return await asyncio.get_running_loop().run_in_executor(p2p.PULLS, self._unpack_batch, key, taken)

    def _unpack_batch(self, key, taken: list[tuple[Envelope, float]]) -> list:
        """The items a batch get took, unpacked (object-store payloads fetched in one round trip).
        One that cannot be (its producer's shared memory or object is gone) raises its error, but
        only after every other item went back to the front of the queue in its order (those already
        read re-packed): one lost item does not take the rest of the batch with it."""
        refs = [envelope.body[0] for envelope, _ in taken if envelope.path == "object_store"]
        try:
            fetched = iter(ray.get(refs)) if len(refs) > 1 else None
        except Exception:  # an object is lost: fetched one at a time below, so the others are kept
            fetched = None
        values: list = []
        for index, (envelope, _) in enumerate(taken):
            try:
                if fetched is not None and envelope.path == "object_store":
                    values.append(unbox(next(fetched)))
                else:
                    values.append(unpack(envelope))
            except Exception:
                back = [(pack(value), weight) for value, (_, weight) in zip(values, taken)] + taken[index + 1:]
                if back:
                    self._call(self._actor.give_back.remote(key, back))
                raise
        return values

    # ------------------------------------------------------------------ internals
    def _pack(self, item: Any) -> Envelope:
        return pack(item, same_process=self._consumers_here_only, force_p2p=self.transport == "p2p",
                    shared_memory=self._shared_memory_reaches_consumers)

    def _shared_memory_reaches_consumers(self) -> bool:
        """Whether every consumer is on this node; a producer's first item that could go by shared
        memory waits for the registration's reply (one round trip per client) to know it."""
        if not self._consumers_known and self._registration is not None:
            registration, self._registration = self._registration, None
            self._note_consumers(self._call(registration))
        return self._consumers_on_this_node

    def _note_consumers(self, consumers: tuple[list, list[str]]) -> None:
        """Learn the consumers from a reply of the channel: their (pid, node), their nodes."""
        seen, nodes = consumers
        # By-reference hand-over is only safe when every consumer seen so far is this process (the
        # same pid on this node: pids repeat across nodes), shared memory only while every live
        # consumer is on this node.
        self._consumers_here_only = bool(seen) and {tuple(c) for c in seen} == {(os.getpid(), _node_id())}
        self._consumers_on_this_node = shared_memory_reaches(_node_id(), nodes)
        self._consumers_known = True

    def _settle_put(self, ref, envelope: Envelope) -> None:
        """Wait for a put's reply; a put the channel refused (or lost with its actor) queued
        nothing, so its envelope is discarded (a cancelled wait may still have queued it)."""
        try:
            self._note_consumers(self._call(ref))
        except CallCancelled:
            raise
        except Exception:
            discard(envelope)
            raise

    def _register(self, role: str, wait: bool = False) -> None:
        """Announce this process as a producer or consumer, once per client and role. Not waited
        for (one more message, sent ahead of the call that needs it) unless ``wait``; a producer's
        reply is read when its first item needs it (see ``_shared_memory_reaches_consumers``)."""
        if role in self._roles:
            return
        self._roles.add(role)
        pid = os.getpid()
        ref = self._actor.register.remote(_peer_id(), role, processes.describe_self(), processes.host_handle(),
                                          _node_id(), pid, processes.start_ticks(pid))
        if role == "producer":
            self._registration = ref
        if wait:
            self._call(ref)

    def _check_weight(self, weight, argument: str) -> float:
        value = _as_float(weight)
        if not value > 0 or math.isinf(value):
            raise ValueError(f"channel '{self.name}': {argument} must be a finite number > 0, got {weight!r}")
        return value

    def _check_target(self, target_weight) -> float:
        if not _as_float(target_weight) > 0:
            raise ValueError(f"channel '{self.name}': target_weight must be a number > 0, got {target_weight!r}")
        return float(target_weight)

    def _call(self, ref, on_cancel=None):
        try:
            return cancellation.wait_ref(ref) if on_cancel is None else _wait_get(ref, on_cancel)
        except CallCancelled:
            raise
        except ray.exceptions.TaskCancelledError:
            # Ray cancels the calls a cancelled call made (recursively), possibly before this
            # call's own cancel token is set: the enclosing call is being cancelled.
            raise cancellation.cancelled_error() from None
        except ray.exceptions.RayTaskError as exc:
            raise _unwrap(exc) from None
        except ray.exceptions.RayActorError:
            raise self._gone() from None

    async def _acall(self, ref, cancel_in_actor: bool = True):
        try:
            return await ref
        except asyncio.CancelledError:
            if cancel_in_actor:  # else the actor's wait goes on, and could still put the item
                cancellation.cancel_quietly(ref)
            raise
        except ray.exceptions.TaskCancelledError:  # as in _call: the awaiting task is being cancelled
            raise asyncio.CancelledError() from None
        except ray.exceptions.RayTaskError as exc:
            raise _unwrap(exc) from None
        except ray.exceptions.RayActorError:
            raise self._gone() from None

    def _get(self, method, *args, key=None, request: str | None = None, **extra):
        """Call the actor's get ``method`` (``key``: its first argument unless given). If this
        call is cancelled, the get is abandoned: it ends without taking anything, or, if it had
        taken items already, they go back to the front of their queue."""
        key = args[0] if key is None else key
        request = request or uuid.uuid4().hex
        ref = method.remote(*args, request=request, node=_node_id(), **extra)
        taken = self._call(ref, on_cancel=lambda: self._actor.abandon.remote(request))
        if cancellation.is_cancelled():
            if taken is not None:
                taken = _as_list(taken)
                # A get_many (the get that says what it handed out) that took more than one item leased
                # them to this process: giving them back ends the lease.
                lease = request if "handed_out" in extra and len(taken) > 1 else None
                self._actor.give_back.remote(key, taken, lease)
            raise cancellation.cancelled_error()
        return taken

    async def _aget(self, method, *args, key=None):
        """As :meth:`_get`, for a caller that awaits: a cancel of the awaiting task abandons the
        get; the clean-up runs shielded, so a second cancel cannot cut it short."""
        key = args[0] if key is None else key
        request = uuid.uuid4().hex
        ref = method.remote(*args, request=request, node=_node_id())
        try:
            return await self._acall(ref, cancel_in_actor=False)
        except asyncio.CancelledError:
            cleanup = asyncio.ensure_future(self._abandon(ref, request, key))
            try:
                await asyncio.shield(cleanup)
            except asyncio.CancelledError:
                pass  # cancelled again: the clean-up goes on by itself
            raise

    async def _abandon(self, ref, request: str, key) -> None:
        try:
            await self._actor.abandon.remote(request)
            taken = await asyncio.wait_for(ref, timeout=ABANDON_WAIT_S)
            if taken is not None:
                await self._actor.give_back.remote(key, _as_list(taken))
        except Exception:  # the get failed (timeout, closed, dead peers) or the actor is gone: nothing taken
            pass

    def _gone(self) -> ChannelError:
        return ChannelError(f"channel '{self.name}' is gone: its actor was destroyed or died")


_UNREAD = object()


def _prefetch_entries(taken: list) -> list[tuple]:
    """``(envelope, weight, value)`` for items a prefetching get took. Object-store payloads are
    fetched now, in one ``ray.get`` (their envelopes stay valid, so they can still be given back);
    the others are unpacked only when handed out, because unpacking consumes them (a same-process
    item, a p2p receive) or maps memory that a given-back item must not keep."""
    refs = [envelope.body[0] for envelope, _ in taken if envelope.path == "object_store"]
    fetched = iter(ray.get(refs)) if refs else iter(())
    return [(envelope, weight, unbox(next(fetched)) if envelope.path == "object_store" else _UNREAD)
            for envelope, weight in taken]


def _wait_get(ref, on_cancel):
    """``cancellation.wait_ref`` for a get: once the call is cancelled it abandons the get again
    from this thread and waits at most ``CANCELLED_GET_WAIT_S`` more for the reply (see there)."""
    return cancellation.wait_ref(ref, on_cancel, cancelled_wait_s=CANCELLED_GET_WAIT_S)


def _unwrap(exc: ray.exceptions.RayTaskError) -> BaseException:
    cause = getattr(exc, "cause", None)
    if isinstance(cause, (ChannelClosed, ChannelError, TimeoutError)):
        return cause
    return exc


def _as_list(taken) -> list[tuple[Envelope, float]]:
    """A get's result as a list of ``(envelope, weight)``: ``get`` returns one pair, the others lists."""
    return taken if isinstance(taken, list) else [taken]


def _as_float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


_node_ids: dict[int, str] = {}  # by pid: a forked process asks again
_peer_ids: dict[int, str] = {}


def _node_id() -> str:
    pid = os.getpid()
    if pid not in _node_ids:
        _node_ids[pid] = ray.get_runtime_context().get_node_id()
    return _node_ids[pid]


def _peer_id() -> str:
    """This process as the channel knows it: a worker rank by its host actor (the same peer after
    Ray restarts it), any other process by node and pid."""
    pid = os.getpid()
    if pid not in _peer_ids:
        if processes.host_handle() is not None:
            _peer_ids[pid] = "actor:" + ray.get_runtime_context().get_actor_id()
        else:
            _peer_ids[pid] = f"process:{_node_id()}:{pid}"
    return _peer_ids[pid]
