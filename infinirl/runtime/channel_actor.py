"""The actor behind a ``Channel``: per-key queues of envelopes, and every wait of the channel.

It holds metadata only (``transport.Envelope``s); payloads move from producer to consumer
directly. All waiting happens here, on one asyncio condition: getters wait for an item of their
key, putters for space in theirs. A wait ends when it can succeed, when the channel closes, or
when it can never succeed because the processes on the other side are gone:

- every process that puts or gets registers as a producer or consumer (its first call does),
- the actor watches each one (a worker rank's host through Ray, any other process on the
  actor's node through its pid) and marks it dead when its process exits for good (a rank that
  Ray restarts is the same peer, alive again),
- a getter that finds no item once every producer has died, or a putter waiting for space once
  every consumer has died, gets ``ChannelPeerDied`` naming the channel, the key and the dead
  processes; a pending get of a consumer that died takes nothing (nobody would receive it).

Items in a producer's shared memory (``transport`` path ``shm``) are pinned to its node: they are
served only to getters on that node, as same-process items are served only to their process. A
producer learns from every put's reply which consumers are registered and on which nodes, and
puts an item in shared memory only while all of them are on its node; a consumer that registers
later on another node gets the items put after its registration is known. Pinned items that no
consumer on their node is left to take (every one of them died) are dropped, and a getter from
another node that finds nothing else is told so (``ChannelPeerDied``) instead of waiting forever.

A prefetching get (``get_many``) hands its caller one item and the rest to hold and hand out
later. Those held items stay *leased* to the calling process until the client says it has handed
them all out, which it says with its next ``get_many`` (no message of its own, none per item) or
with ``give_back``/``settle_leases`` when it stops. When the process dies, or a rank's process is
replaced by a restart, its leases go back to the front of their queues, in order, and the channel
logs how many: without a message per item the channel cannot know which items of a lease the
process had handed out already, so those it had are delivered a second time, to another process.
A living process never loses its lease: there is no lease timeout, a slow consumer is not a dead one.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import ray

from infinirl.runtime import processes
from infinirl.runtime.call_order import CallOrder
from infinirl.runtime.errors import ChannelClosed, ChannelError, ChannelPeerDied
from infinirl.runtime.transport import Envelope, pinned_node, pinned_pid

__all__ = ["ChannelActor"]

logger = logging.getLogger(__name__)

# A watch call on a rank's host returns after this long and is renewed: a watch that outlives
# its channel (destroyed, or its owner gone) ends by itself instead of holding a slot in the host.
WATCH_RENEW_S = 30.0
# How often a process without a host (the driver, a plain Ray task) on this node is checked.
PID_POLL_S = 1.0
# An abandoned request id whose get never arrives (it had finished already) is forgotten after this.
ABANDONED_KEEP_S = 600.0


class _Item:
    __slots__ = ("envelope", "weight", "pinned_pid", "pinned_node")

    def __init__(self, envelope: Envelope, weight: float):
        self.envelope = envelope
        self.weight = weight
        self.pinned_pid = pinned_pid(envelope)  # only this process can unpack it
        self.pinned_node = pinned_node(envelope)  # only processes on this node can

    def serves(self, pid: int, node: str | None) -> bool:
        if self.pinned_pid is not None:  # the producer's own process: same pid on the same node
            return self.pinned_pid == pid and self.envelope.producer_node == node
        return self.pinned_node is None or self.pinned_node == node


@dataclass
class _Peer:
    description: str
    node: str
    roles: set[str] = field(default_factory=set)
    death: str = ""  # why it is dead, once it is
    process: tuple | None = None  # a rank's current process, (node, pid), as its host last said
    requeued: int = 0  # items of its leases that went back to the queues when its process ended


@dataclass
class _Lease:
    """Items a prefetching get took for one process beyond the one it handed out at once."""
    peer_id: str
    process: tuple  # (node, pid) of the process that holds them
    key: Any
    items: list[_Item]


class ChannelActor:
    """Run as an async Ray actor (``Channel.create`` starts it); see the module docstring."""

    def __init__(self, name: str, maxsize: float, transport: str = "auto", pipeline_depth: int = 0,
                 prefetch: int = 1):
        self.name = name
        self.transport = transport
        self.pipeline_depth = pipeline_depth
        self.prefetch = prefetch
        self.maxsize = maxsize  # per key, in weight units; 0: unbounded
        self.queues: dict[Any, deque[_Item]] = {}
        self.weight_by_key: dict[Any, float] = {}
        self.closed = False
        self.cond = asyncio.Condition()
        self.order = CallOrder()
        self.consumers: set[tuple[int, str | None]] = set()  # (pid, node): pids repeat across nodes
        self.peers: dict[str, _Peer] = {}
        self.watches: set[asyncio.Task] = set()
        self.node_id = ray.get_runtime_context().get_node_id()
        self.stats = {"put": 0, "get": 0, "requeued_from_dead": 0, "lost_with_dead": 0}
        self.abandoned: dict[str, float] = {}  # request id -> when it was abandoned
        self.leases: dict[str, _Lease] = {}  # by the request id of the get that took them

    # ------------------------------------------------------------------ peers
    async def register(self, peer_id: str, role: str, description: str, host, node_id: str, pid: int,
                       start: int) -> tuple[list[int], list[str]]:
        """A producer or consumer announces itself (once per role); its death is watched from now.
        Returns what a put returns: the consumers known so far."""
        peer = self.peers.get(peer_id)
        if peer is None:
            peer = self.peers[peer_id] = _Peer(description, node_id)
            task = asyncio.ensure_future(self._watch(peer_id, host, node_id, pid, start))
            self.watches.add(task)
            task.add_done_callback(self.watches.discard)
        peer.node = node_id  # a rank that Ray restarted may run on another node now
        peer.roles.add(role)
        return self._consumers()

    def _consumers(self) -> tuple[list[tuple[int, str | None]], list[str]]:
        """What a producer needs to pick an item's path: the (pid, node) of the consumers seen so far
        (for same-process items), the nodes of the live registered consumers (for shared memory)."""
        return sorted(self.consumers, key=str), sorted(self._live_consumer_nodes())

    def _live_consumer_nodes(self) -> set[str]:
        return {p.node for p in self.peers.values() if "consumer" in p.roles and not p.death}

    async def register_consumer(self, pid: int, node: str | None = None) -> None:
        self.consumers.add((pid, node))

    async def _watch(self, peer_id: str, host, node_id: str, pid: int, start: int) -> None:
        if host is not None:
            self.peers[peer_id].process = await _host_process(host)
            death = await until_host_dies(host, lambda: self._host_back(peer_id, host))
        elif node_id == self.node_id:
            while processes.alive(pid, start):
                await asyncio.sleep(PID_POLL_S)
            death = "its process exited"
        else:
            return  # a process without a host on another node: nothing here can watch it
        async with self.cond:
            self.peers[peer_id].death = death
            self._release_leases(peer_id, lambda lease: True, "died")
            self.cond.notify_all()

    async def _host_back(self, peer_id: str, host) -> bool:
        """A rank's host answers again after a call to it failed: if Ray restarted it, the leases
        of its old process go back (the new process does not hold them); if it was only
        unreachable for a while, its process is the same and keeps them. False if the host could
        not be asked (the watch asks again once it answers)."""
        process = await _host_process(host)
        if process is None:
            return False
        async with self.cond:
            peer = self.peers[peer_id]
            old, peer.process = peer.process, process
            if old != process:
                # Old process unknown (the first question failed): every lease not held by the new
                # process is the old one's, as a rank runs one process at a time.
                ended = (lambda lease: lease.process == old) if old else (lambda lease: lease.process != process)
                self._release_leases(peer_id, ended, "was restarted by Ray (a new process took its place)")
        return True

    def _release_leases(self, peer_id: str, which, what: str) -> None:
        """Put the items of ``peer_id``'s leases that ``which`` picks back at the front of their
        queues, in their order, and say so: their process has ended. Items only that process
        could read (same-process items) are dropped and counted as lost."""
        ended = [lease_id for lease_id, lease in self.leases.items() if lease.peer_id == peer_id and which(lease)]
        if not ended:
            return
        requeued = lost = 0
        for lease_id in reversed(ended):  # the latest first: the earliest ends up at the front
            lease = self.leases.pop(lease_id)
            readable = [item for item in lease.items if item.pinned_pid is None]
            self._give_back(lease.key, readable)
            requeued += len(readable)
            lost += len(lease.items) - len(readable)
        peer = self.peers.get(peer_id)
        if peer is not None:
            peer.requeued += requeued
        self.stats["requeued_from_dead"] += requeued
        self.stats["lost_with_dead"] += lost
        logger.warning(
            "channel '%s': consumer %s %s holding %d item(s) it had taken ahead (prefetch); %d went back to the "
            "front of their queues for the other consumers (the ones it had handed out since its last get may be "
            "delivered again)%s", self.name, peer.description if peer else peer_id, what, requeued + lost, requeued,
            f", {lost} lived in its own memory and are lost" if lost else "")

    def _all_dead(self, role: str) -> list[_Peer]:
        """The peers of ``role`` if every one of them has died, else [] (also when none is known)."""
        peers = [p for p in self.peers.values() if role in p.roles]
        return peers if peers and all(p.death for p in peers) else []

    def _is_dead(self, peer_id: str) -> bool:
        peer = self.peers.get(peer_id)
        return bool(peer and peer.death)

    def _died(self, what: str, peers: list[_Peer]) -> ChannelPeerDied:
        dead = "; ".join(f"{p.description}: {p.death}" for p in peers)
        return ChannelPeerDied(f"channel '{self.name}': {what} [{dead}]")

    # ------------------------------------------------------------------ put
    async def put(self, envelope: Envelope, key, weight: float, timeout: float | None,
                  producer: str | None = None, seq: int = -1):
        if seq < 0:
            return await self._put(envelope, key, weight, timeout)
        # Pipelined producers number their puts: Ray does not promise that an async actor starts
        # calls in submission order, and per-producer FIFO must hold.
        await self.order.wait_turn(producer, seq)
        try:
            return await self._put(envelope, key, weight, timeout)
        finally:
            self.order.end_turn(producer, seq)

    async def _put(self, envelope: Envelope, key, weight: float, timeout: float | None):
        if self.closed:
            raise ChannelClosed(f"put on closed channel '{self.name}' (key {key!r})")
        if self.maxsize and weight > self.maxsize:
            raise ChannelError(
                f"channel '{self.name}': an item of weight {weight} can never fit maxsize={self.maxsize} "
                f"(key {key!r}); raise maxsize or split the item"
            )
        async with self.cond:
            if self.maxsize:
                await self._wait_for(
                    lambda: self._fits(key, weight) or self.closed or self._all_dead("consumer"),
                    _deadline(timeout), f"put on key {key!r}", timeout)
                if self.closed:
                    raise ChannelClosed(f"channel '{self.name}' closed while a put on key {key!r} waited for space")
                if not self._fits(key, weight):
                    raise self._died(f"a put on key {key!r} waits for space (maxsize={self.maxsize} per key) and "
                                     "every consumer of the channel has died", self._all_dead("consumer"))
            self.queues.setdefault(key, deque()).append(_Item(envelope, weight))
            self.weight_by_key[key] = self.weight_by_key.get(key, 0.0) + weight
            self.stats["put"] += 1
            self.cond.notify_all()
        return self._consumers()

    def _fits(self, key, weight: float) -> bool:
        return self.weight_by_key.get(key, 0.0) + weight <= self.maxsize

    async def put_many(self, envelopes: list[Envelope], key, weights: list[float], timeout,
                       producer: str | None = None, seq: int = -1):
        """The items in order, as one numbered call of a pipelined producer (``seq`` >= 0)."""
        if seq >= 0:
            await self.order.wait_turn(producer, seq)  # outside the try: a cancelled wait gives its turn up
        try:
            for envelope, weight in zip(envelopes, weights):
                await self._put(envelope, key, weight, timeout)
        finally:
            if seq >= 0:
                self.order.end_turn(producer, seq)
        return self._consumers()

    # ------------------------------------------------------------------ get
    def _eligible(self, key, pid: int, node: str | None) -> int | None:
        """The index of the oldest item of ``key`` that the getter ``pid`` on ``node`` can unpack."""
        queue = self.queues.get(key)
        if not queue:
            return None
        for index, item in enumerate(queue):
            if item.serves(pid, node):
                return index
        return None

    def _stranded(self, key, node: str | None) -> list[_Item]:
        """The items of ``key`` pinned to another node than ``node`` where no live consumer is left."""
        queue = self.queues.get(key)
        pinned = [item for item in queue or () if item.pinned_node is not None and item.pinned_node != node]
        if not pinned:
            return []
        live = self._live_consumer_nodes()
        return [item for item in pinned if item.pinned_node not in live]

    def _drop_stranded(self, key, node: str | None, stranded: list[_Item]) -> ChannelPeerDied:
        """Remove ``stranded`` items from their queue; the error that tells the getter on ``node``."""
        queue = self.queues[key]
        for item in stranded:
            queue.remove(item)
            self.weight_by_key[key] -= item.weight
        if not queue:
            del self.queues[key], self.weight_by_key[key]
        self.cond.notify_all()  # room for waiting putters
        nodes = sorted({item.pinned_node for item in stranded})
        return ChannelPeerDied(
            f"channel '{self.name}': {len(stranded)} item(s) of key {key!r} were put in shared memory on node(s) "
            f"{nodes} for the consumers there, and every consumer on those nodes has died; a getter on node {node} "
            "cannot read them: they are dropped")

    def _can_end_get(self, key, pid: int, node: str | None, peer_id: str, request: str | None) -> bool:
        return (request in self.abandoned or self._eligible(key, pid, node) is not None or self.closed
                or self._is_dead(peer_id) or bool(self._all_dead("producer")) or bool(self._stranded(key, node)))

    def _takeable(self, key, pid: int, node: str | None, peer_id: str, drop_stranded: bool = True) -> int:
        """The index of the item to take, once a get's wait ended; else the error that ends it.
        ``drop_stranded=False``: a get that returns with items already taken leaves stranded items
        to the next get, which drops them and reports it."""
        if self._is_dead(peer_id):
            raise self._died(f"the consumer waiting for key {key!r} died", [self.peers[peer_id]])
        index = self._eligible(key, pid, node)
        if index is not None:
            return index
        stranded = self._stranded(key, node)
        if stranded and drop_stranded:
            raise self._drop_stranded(key, node, stranded)
        if stranded:
            raise ChannelPeerDied(f"channel '{self.name}': items of key {key!r} are stranded on another node")
        if self.closed:
            raise ChannelClosed(f"channel '{self.name}' is closed and has no more items for key {key!r}")
        raise self._died(f"no item for key {key!r} and every producer of the channel has died",
                         self._all_dead("producer"))

    def _take(self, key, index: int) -> _Item:
        queue = self.queues[key]
        if index == 0:
            item = queue.popleft()
        else:
            item = queue[index]
            del queue[index]
        self.weight_by_key[key] -= item.weight
        if not queue:  # keys may be one-off (one per generation): an empty one holds nothing
            del self.queues[key], self.weight_by_key[key]
        self.stats["get"] += 1
        return item

    def _give_back(self, key, items: list[_Item]) -> None:
        """Return taken items to the front of their queue, in their order (a get that cannot
        deliver them must not lose them)."""
        if not items:
            return
        self.queues.setdefault(key, deque()).extendleft(reversed(items))
        self.weight_by_key[key] = self.weight_by_key.get(key, 0.0) + sum(i.weight for i in items)
        self.stats["get"] -= len(items)
        self.cond.notify_all()

    async def give_back(self, key, taken: list[tuple[Envelope, float]], lease: str | None = None) -> int:
        """Items a get took for a caller that was cancelled before it received them, or that a
        prefetching client did not hand out (``lease``: the get that took them, whose lease this
        ends). Returns how many went back: none if the lease had already been put back because
        its process was taken for dead (they must not be queued twice)."""
        async with self.cond:
            if lease is not None and self.leases.pop(lease, None) is None:
                return 0
            self._give_back(key, [_Item(envelope, weight) for envelope, weight in taken])
        return len(taken)

    async def settle_leases(self, leases: list[str]) -> None:
        """A prefetching client handed out every item of these leases: they are its caller's now."""
        for lease in leases:
            self.leases.pop(lease, None)

    async def abandon(self, request: str) -> None:
        """The caller of get ``request`` was cancelled: that get ends without taking anything."""
        now = time.monotonic()
        async with self.cond:
            for old in [r for r, since in self.abandoned.items() if now - since > ABANDONED_KEEP_S]:
                del self.abandoned[old]
            self.abandoned[request] = now
            self.cond.notify_all()

    def _was_abandoned(self, request: str | None) -> bool:
        return self.abandoned.pop(request, None) is not None if request is not None else False

    async def get(self, key, pid: int, peer_id: str, timeout: float | None, request: str | None = None,
                  node: str | None = None):
        """The oldest item of ``key`` that the getter (``pid`` on ``node``) can unpack, as
        ``(envelope, weight)``; ``None`` if abandoned."""
        taken = await self.get_many(key, pid, peer_id, 1, timeout, request, node)
        return None if taken is None else taken[0]

    async def get_many(self, key, pid: int, peer_id: str, max_items: int, timeout: float | None,
                       request: str | None = None, node: str | None = None, handed_out: list[str] = ()):
        """Wait for one item, then also take up to ``max_items - 1`` more already waiting (prefetch);
        ``None`` if abandoned. The items beyond the first are leased to the caller's process under
        ``request`` until a later call lists it in ``handed_out`` (or gives them back)."""
        for lease in handed_out:  # before any wait: settled even if this get then fails
            self.leases.pop(lease, None)
        self.consumers.add((pid, node))
        async with self.cond:
            await self._wait_for(lambda: self._can_end_get(key, pid, node, peer_id, request), _deadline(timeout),
                                 f"get on key {key!r}", timeout)
            if self._was_abandoned(request):
                return None
            taken = [self._take(key, self._takeable(key, pid, node, peer_id))]
            while len(taken) < max_items and (index := self._eligible(key, pid, node)) is not None:
                taken.append(self._take(key, index))
            if len(taken) > 1 and request is not None:
                self.leases[request] = _Lease(peer_id, (node, pid), key, taken[1:])
            self.cond.notify_all()
            return [(item.envelope, item.weight) for item in taken]

    async def get_batch(self, target_weight: float, key, pid: int, peer_id: str, timeout: float | None,
                        request: str | None = None, node: str | None = None):
        """Items of ``key`` in FIFO order while their total weight stays within ``target_weight``;
        returns once the total equals it, once the next item would exceed it, or (with what it
        has) once the channel is closed and drained, every producer died, or the timeout expired.
        An item heavier than the target comes alone. ``None`` if abandoned (nothing taken)."""
        self.consumers.add((pid, node))
        deadline = _deadline(timeout)
        taken: list[_Item] = []
        total = 0.0
        async with self.cond:
            try:
                while total < target_weight:
                    try:
                        await self._wait_for(lambda: self._can_end_get(key, pid, node, peer_id, request),
                                             deadline, f"get_batch on key {key!r}", timeout)
                        if self._was_abandoned(request):
                            self._give_back(key, taken)
                            return None
                        index = self._takeable(key, pid, node, peer_id, drop_stranded=not taken)
                    except (TimeoutError, ChannelClosed, ChannelPeerDied):
                        if taken and not self._is_dead(peer_id):
                            break
                        raise
                    weight = self.queues[key][index].weight
                    if taken and total + weight > target_weight:
                        break
                    taken.append(self._take(key, index))
                    total += weight
                    self.cond.notify_all()
            except BaseException:  # cancelled, or its consumer died: nothing taken is lost
                self._give_back(key, taken)
                raise
        return [(item.envelope, item.weight) for item in taken]

    # ------------------------------------------------------------------ lifecycle / introspection
    async def close(self) -> None:
        async with self.cond:
            self.closed = True
            self.cond.notify_all()

    async def queued(self) -> list[Envelope]:
        """The envelopes in the queues (not the leased ones: a consumer still holds those), for
        producers to drop what they hold for them when the channel is destroyed."""
        return [item.envelope for queue in self.queues.values() for item in queue]

    async def qsize(self, key=None) -> int:
        if key is None:
            return sum(len(q) for q in self.queues.values())
        return len(self.queues.get(key, ()))

    async def info(self) -> dict:
        return {"name": self.name, "maxsize": self.maxsize, "closed": self.closed, "transport": self.transport,
                "pipeline_depth": self.pipeline_depth, "prefetch": self.prefetch,
                "weight_in_queue": sum(self.weight_by_key.values()),
                "weight_by_key": {repr(k): w for k, w in self.weight_by_key.items() if w},
                "leased": sum(len(lease.items) for lease in self.leases.values()),
                "peers": {p.description: {"roles": sorted(p.roles), "death": p.death, "requeued": p.requeued}
                          for p in self.peers.values()},
                **self.stats}

    async def _wait_for(self, predicate, deadline: float | None, what: str, timeout: float | None) -> None:
        if predicate():  # asyncio.wait_for with no time left cancels the wait before it checks anything
            return
        remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
        try:
            await asyncio.wait_for(self.cond.wait_for(predicate), remaining)
        except asyncio.TimeoutError:
            raise TimeoutError(f"channel '{self.name}': {what} timed out after {timeout}s") from None


def _deadline(timeout: float | None) -> float | None:
    return None if timeout is None or math.isinf(timeout) else time.monotonic() + timeout


async def until_host_dies(host, on_back=None) -> str:
    """Wait until a worker rank's host actor is dead for good; returns why. A rank that Ray
    restarts is alive again once restarted, and watched on. ``on_back`` (a coroutine function
    returning whether it reached the host) runs each time the host answers again after a call
    to it failed, until it reaches it: a rank that Ray restarts fails this watch's call, and
    nothing else tells the watch that its process changed."""
    while True:
        try:
            await host.alive_for.options(max_task_retries=0).remote(WATCH_RENEW_S)
            continue
        except ray.exceptions.RayActorError:
            pass
        while True:
            try:
                await host.__ray_ready__.remote()  # waits out a restart; fails if the actor is dead
            except ray.exceptions.ActorDiedError:
                return "its process exited"
            except ray.exceptions.RayActorError:
                await asyncio.sleep(PID_POLL_S)  # unavailable for now: ask again
                continue
            if on_back is None or await on_back():
                break
            await asyncio.sleep(PID_POLL_S)  # it failed again before it could be asked


async def _host_process(host) -> tuple | None:
    """The (node, pid) of the process a rank's host runs in now; None if it cannot answer."""
    try:
        return tuple(await host.process.options(max_task_retries=0).remote())
    except ray.exceptions.RayActorError:
        return None
