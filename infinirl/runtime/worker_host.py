"""The Ray actor that hosts one ``Worker`` rank, and what the rank knows about where it runs.

``WorkerGroup.launch`` starts one ``WorkerHost`` per rank. The host builds the rank's ``Worker``
and runs its methods: synchronous ones one at a time, in call order, on one dedicated compute
thread (so torch state and CUDA's per-thread device stay consistent); ``async def`` ones
concurrently on the actor's event loop. Every exception of a method becomes a ``WorkerError``
naming the rank, the method and the original traceback; a hard crash leaves the process's
Python stacks in the rank's crash log (``crash_logs``).
"""

from __future__ import annotations

import asyncio
import inspect
import os
import socket
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import ray

from infinirl.runtime import crash_logs, p2p, processes, rendezvous
from infinirl.runtime.call_order import CallOrder
from infinirl.runtime.cancellation import CancelToken, run_with_token
from infinirl.runtime.compute_thread import mark_compute_thread
from infinirl.runtime.errors import WorkerError
from infinirl.runtime.placement import is_visible_devices_variable, physical_visible_devices

__all__ = ["RankContext", "WorkerHost"]

# How many recent results' types a host remembers, to name the one Ray could not send back.
_RETURNED_TYPES_KEPT = 256


@dataclass
class RankContext:
    """Everything a rank knows about where it runs; built by the group, read by the Worker."""

    component: str
    rank: int
    world_size: int
    node_id: str | None = None
    node_ip: str = ""
    local_devices: tuple[int, ...] = ()
    cpu_slots: tuple[int, ...] = ()
    robot: Any = None
    env_vars: dict[str, str] = field(default_factory=dict)
    #: the rank's crash log in ``CRASH_LOG_DIR`` on its node, named by the group at launch so that
    #: the driver knows it even when the rank fails to start, and a restarted process reuses it
    crash_log_name: str = ""
    #: where the group's torch.distributed rendezvous is published (``rendezvous``): rank 0 hosts
    #: it, every rank has MASTER_ADDR/MASTER_PORT from it before its Worker is built
    rendezvous_key: str = ""


def _quiet_ray_async_warnings() -> None:
    """Sync methods run on their own thread, where a blocking ``ray.get`` cannot stall the event
    loop; Ray cannot tell and warns on the first one, so mark that warning as already given."""
    try:
        import ray._private.worker as ray_worker

        ray_worker.blocking_get_inside_async_warned = True
    except Exception:
        pass


def _was_reconstructed() -> bool:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the property is deprecated in favour of nothing equivalent
        return bool(ray.get_runtime_context().was_current_actor_reconstructed)


def _construct(worker_cls: type, ctx: RankContext, args: tuple, kwargs: dict):
    worker = worker_cls.__new__(worker_cls)
    worker.ctx = ctx
    worker.__init__(*args, **kwargs)
    return worker


class WorkerHost:
    """Run as a Ray actor, one per rank; turns every failure into a ``WorkerError``."""

    def __init__(self, worker_cls: type, ctx: RankContext, args: tuple, kwargs: dict):
        os.environ.update({name: physical_visible_devices(name, value, os.environ.get(name))
                           if is_visible_devices_variable(name) else value for name, value in ctx.env_vars.items()})
        _quiet_ray_async_warnings()
        self._restarted = _was_reconstructed()
        self._ctx = ctx
        self._spans: list[tuple] = []
        self._sync_executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="infinirl-sync",
                                                 initializer=mark_compute_thread)
        self._sync_executor.submit(lambda: None)  # start the thread now: it is the compute thread from here on
        self._init_error: WorkerError | None = None
        self._order = CallOrder()
        self._returned_types: dict[tuple[str, int], str] = {}
        self._node_ip = ray.util.get_node_ip_address()
        ctx.node_ip = ctx.node_ip or self._node_ip
        self._crash_log = crash_logs.enable(ctx.component, ctx.rank, ctx.crash_log_name)
        processes.register_host(ray.get_runtime_context().current_actor, f"{ctx.component}[rank {ctx.rank}]")
        self._rendezvous_store = None  # rank 0's: held for the life of the process
        try:
            self._join_rendezvous(ctx)
            # On the compute thread, like every sync method: the constructor builds models and
            # may run parallel torch ops, and one OpenMP team on a second thread makes libgomp
            # count more threads than cores and stop spin-waiting for every team in the process
            # (see compute_thread), which slows every later parallel region of the rank.
            self._worker = self._sync_executor.submit(_construct, worker_cls, ctx, args, kwargs).result()
        except BaseException:  # reported on the first call (see ready())
            self._worker = None
            self._init_error = self._error("__init__", traceback.format_exc())

    def _join_rendezvous(self, ctx: RankContext) -> None:
        """MASTER_ADDR/MASTER_PORT of the group's torch.distributed rendezvous, in the environment
        before the Worker is built (its constructor may form the group): rank 0 binds it, the
        others wait until rank 0 has published it."""
        if not ctx.rendezvous_key:
            return
        if ctx.rank == 0:
            addr, port, self._rendezvous_store = rendezvous.host_master(ctx.rendezvous_key)
        else:
            addr, port = rendezvous.await_master(ctx.rendezvous_key)
        master = {"MASTER_ADDR": addr, "MASTER_PORT": str(port)}
        os.environ.update(master)
        ctx.env_vars.update(master)

    def _error(self, method: str, text: str, cause: str = "raised") -> WorkerError:
        return WorkerError(
            component=self._ctx.component,
            rank=self._ctx.rank,
            method=method,
            node_ip=self._node_ip,
            hostname=socket.gethostname(),
            pid=os.getpid(),
            traceback_text=text,
            cause=cause,
        )

    async def ready(self) -> dict:
        if self._init_error is not None:
            raise self._init_error
        return {
            "node_ip": self._node_ip,
            "node_id": ray.get_runtime_context().get_node_id(),
            "pid": os.getpid(),
            "hostname": socket.gethostname(),
            "crash_log": self._crash_log,
            "restarted": self._restarted,
        }

    async def execute(self, method: str, args: tuple, kwargs: dict, caller: str = "", seq: int = -1) -> Any:
        """Run one call. Calls from one caller *start* in the order they were made (Ray's async
        actors do not guarantee it); sync ones then run FIFO on the single executor thread.

        Cancelled (Ray cancels this coroutine): a call still waiting for its turn gives the turn
        up; an async method is cancelled where it awaits; a sync method's ``CancelToken`` is
        cancelled, which ends its runtime waits (channel gets and puts) with ``CallCancelled``."""
        if self._init_error is not None:
            raise self._init_error
        fn = getattr(self._worker, method)
        if seq >= 0:
            await self._order.wait_turn(caller, seq, resume=self._restarted)
        start = time.time()
        ok = False
        token = None
        try:
            if inspect.iscoroutinefunction(fn):
                pending = asyncio.ensure_future(fn(*args, **kwargs))
            else:
                token = CancelToken(f"{self._ctx.component}[rank {self._ctx.rank}].{method}()")
                loop = asyncio.get_running_loop()
                pending = loop.run_in_executor(self._sync_executor, run_with_token, token, fn, args, kwargs)
        finally:
            if seq >= 0:
                self._order.end_turn(caller, seq)
        try:
            result = await pending
            ok = True
            self._note_returned_type(caller, seq, result)
            return result
        except asyncio.CancelledError:
            if token is not None:
                token.cancel()
            raise
        except BaseException:
            raise self._error(method, traceback.format_exc()) from None
        finally:
            self._spans.append((self._ctx.component, self._ctx.rank, method, start, time.time(), ok))

    def _note_returned_type(self, caller: str, seq: int, result: Any) -> None:
        if seq < 0:
            return
        kind = type(result)
        self._returned_types[(caller, seq)] = f"{kind.__module__}.{kind.__qualname__}"
        if len(self._returned_types) > _RETURNED_TYPES_KEPT:
            del self._returned_types[next(iter(self._returned_types))]

    async def skip_call(self, caller: str, seq: int) -> None:
        """Call ``seq`` of ``caller`` will not arrive (or must not run): later calls stop waiting for it."""
        self._order.skip(caller, seq)

    async def returned_type(self, caller: str, seq: int) -> str | None:
        """The type of what call ``seq`` of ``caller`` returned (None: unknown, or it never ran);
        asked by the driver when Ray could not send a result back."""
        return self._returned_types.get((caller, seq))

    async def alive_for(self, seconds: float) -> None:
        """Returns after ``seconds``: a channel watching this rank calls it again and again, and
        learns from the call's failure that the process died."""
        await asyncio.sleep(seconds)

    async def process(self) -> tuple[str, int]:
        """(node id, pid) of this rank's process: a channel compares it after the rank comes back
        from a failed call, to tell a restart (a new process) from a pause (the same one)."""
        return ray.get_runtime_context().get_node_id(), os.getpid()

    async def _infinirl_p2p_serve(self, item: int, key: tuple, addr: str, port: int, backend: str) -> int:
        """Send a p2p channel item to the consumer that pulls it (runs beside the worker's method)."""
        return await p2p.serve_async(item, key, addr, port, backend)

    async def _infinirl_p2p_release(self, item: int) -> None:
        p2p.release(item)

    async def pop_spans(self) -> list[tuple]:
        spans, self._spans = self._spans, []
        return spans

    async def free_port(self) -> int:
        with socket.socket() as sock:
            sock.bind(("", 0))
            return sock.getsockname()[1]
