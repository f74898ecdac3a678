"""Time-sharing devices between collocated components: a cluster-wide device lock.

Collocated components (e.g. rollout and actor on the same GPUs) take turns: the one whose turn it
is holds the lock of every device it uses, ``reload()``s its state onto them, works, ``offload()``s
and releases. The lock is a named async Ray actor, so any worker on any node can take it, and it
grants devices in FIFO order (no starvation). Locks are keyed by (node, device) so multi-node plans
work; on CPU-only clusters the key is the CPU slot, which keeps the same program meaningful there.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections import deque

import ray

from infinirl.runtime import processes
from infinirl.runtime.ray_defaults import NAMESPACE

LOCK_ACTOR_NAME = "infinirl.device_lock"


class _DeviceLockActor:
    def __init__(self):
        self.owner: dict[str, str] = {}
        self.waiters: deque[tuple[frozenset, str, asyncio.Event]] = deque()
        self.history: list[tuple[str, float, float]] = []
        self.watches: dict[str, asyncio.Task] = {}  # holder -> the task that frees its devices if it dies

    async def acquire(self, devices: list[str], holder: str, timeout: float | None, host=None) -> float:
        """Wait (FIFO) until ``holder`` owns every one of ``devices``; returns the seconds waited.
        ``host``: the holder's worker host actor; should its process die holding the devices,
        they are released, so a crashed holder never blocks the others for good."""
        want = frozenset(devices)
        event = asyncio.Event()
        self.waiters.append((want, holder, event))
        self._grant()
        start = time.time()
        try:
            await asyncio.wait_for(event.wait(), timeout)
        except (asyncio.TimeoutError, asyncio.CancelledError) as exc:
            if event.is_set():  # granted in the same pass as the timeout or the cancellation
                if isinstance(exc, asyncio.CancelledError):  # nobody will use or release them
                    await self.release(list(want), holder)
                    raise
                return self._granted(holder, host, start)
            self.waiters = deque(w for w in self.waiters if w[2] is not event)
            self._grant()  # those behind this waiter may go now
            if isinstance(exc, asyncio.CancelledError):
                raise
            busy = {d: self.owner[d] for d in want if d in self.owner}
            raise TimeoutError(f"{holder} waited {timeout}s for devices held by {busy}") from None
        return self._granted(holder, host, start)

    def _granted(self, holder: str, host, start: float) -> float:
        if host is not None and holder not in self.watches:
            self.watches[holder] = asyncio.ensure_future(self._free_when_dead(holder, host))
        return time.time() - start

    async def _free_when_dead(self, holder: str, host) -> None:
        from infinirl.runtime.channel_actor import until_host_dies

        await until_host_dies(host)
        self.watches.pop(holder, None)
        await self.release([d for d, owner in self.owner.items() if owner == holder], holder)

    async def release(self, devices: list[str], holder: str) -> None:
        for device in devices:
            if self.owner.get(device) == holder:
                del self.owner[device]
        if holder not in self.owner.values():
            watch = self.watches.pop(holder, None)
            if watch is not None:
                watch.cancel()
        self._grant()

    def _grant(self) -> None:
        # FIFO: a waiter is granted only if no earlier waiter wants an overlapping device.
        blocked: set[str] = set()
        remaining = deque()
        for want, holder, event in self.waiters:
            if not (want & blocked) and not any(d in self.owner for d in want):
                for device in want:
                    self.owner[device] = holder
                event.set()
            else:
                blocked |= want
                remaining.append((want, holder, event))
        self.waiters = remaining

    async def holders(self) -> dict[str, str]:
        return dict(self.owner)


def device_lock_actor():
    return (
        ray.remote(_DeviceLockActor)
        .options(name=LOCK_ACTOR_NAME, namespace=NAMESPACE, get_if_exists=True, num_cpus=0, max_concurrency=1000)
        .remote()
    )


def device_keys(worker) -> list[str]:
    ctx = worker.ctx
    node = ctx.node_id or "local"
    if ctx.local_devices:
        return [f"{node}:gpu{d}" for d in ctx.local_devices]
    return [f"{node}:cpu{s}" for s in (ctx.cpu_slots or (ctx.rank,))]


@contextlib.contextmanager
def device_turn(worker, timeout: float | None = None, devices: list[str] | None = None):
    """Hold this rank's devices: reload on entry, offload on exit. Usable in any Worker method."""
    lock = device_lock_actor()
    keys = devices or device_keys(worker)
    holder = f"{worker.component}[{worker.rank}]@{os.getpid()}"
    ray.get(lock.acquire.remote(keys, holder, timeout, processes.host_handle()))
    try:
        worker.reload()
        yield
    finally:
        try:
            worker.offload()
        finally:
            ray.get(lock.release.remote(keys, holder))
