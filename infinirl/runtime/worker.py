"""Worker and WorkerGroup: a component's ranks as Ray actors, with fan-out calls and clear failures.

A ``Worker`` subclass holds the logic of one component rank (an actor trainer, a rollout engine,
an env server...). ``WorkerGroup.launch`` starts one Ray actor per rank, each with
RANK/WORLD_SIZE/MASTER_ADDR/MASTER_PORT set so a torch.distributed group can form on demand
(``Worker.init_process_group``). ``group.method(...)`` fans a call out to all (or chosen) ranks and
returns a ``GroupHandle`` at once: ``wait()``, ``await``, ``done()``.

Execution inside a rank: synchronous methods run one at a time, in call order, on one dedicated
thread (so torch state and CUDA's per-thread device stay consistent); ``async def`` methods run
concurrently on the actor's event loop (e.g. a server loop next to a status query).

Failure reporting is the point of this module. An exception in any rank reaches the driver as one
``WorkerError`` naming component, rank, node, host, method and the original traceback, raised as
soon as the *first* rank fails (other ranks blocked in a collective would otherwise hang or fail
with a secondary error). A rank whose process died is reported with its crash log, not as an
opaque "actor died".
"""

from __future__ import annotations

import asyncio
import difflib
import faulthandler
import inspect
import os
import socket
import tempfile
import time
import traceback
import uuid
import weakref
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from infinirl.runtime.cluster import NAMESPACE, worker_env
from infinirl.runtime.compute_thread import mark_compute_thread
from infinirl.runtime.errors import WorkerError

CRASH_LOG_DIR = Path(tempfile.gettempdir()) / "infinirl-crash-logs"
_CRASH_LOG_PROCESS = "# infinirl worker process "  # + pid: where each process's section of a crash log starts


@dataclass(frozen=True)
class RestartPolicy:
    """For stateless components (env, reward): restart a dead rank up to ``max_restarts`` times.

    With ``retry_calls`` the call that was running when the process died is re-sent to the new
    process, so the driver sees a result instead of an error.
    """

    max_restarts: int = 3
    retry_calls: bool = True


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


class Worker:
    """Base class of every component rank. Subclass it; its methods become remotely callable.

    The runtime sets ``self.ctx`` (a ``RankContext``) *before* your ``__init__`` runs, so
    ``self.rank`` / ``self.world_size`` are usable there.
    """

    ctx: RankContext

    # -- identity ---------------------------------------------------------------------------
    @property
    def rank(self) -> int:
        return self.ctx.rank

    @property
    def world_size(self) -> int:
        return self.ctx.world_size

    @property
    def component(self) -> str:
        return self.ctx.component

    @property
    def device(self) -> str:
        """``"cuda"`` (the first visible device) when this rank was given a GPU, else ``"cpu"``."""
        if self.ctx.local_devices:
            import torch

            if torch.cuda.is_available():
                return "cuda"
        return "cpu"

    # -- collectives ------------------------------------------------------------------------
    def init_process_group(self, backend: str | None = None, timeout_s: float = 600.0) -> None:
        """Form this component's torch.distributed group (gloo on CPU, NCCL on GPU) on demand."""
        import datetime

        import torch
        import torch.distributed as dist

        if dist.is_initialized():
            return
        if backend is None:
            backend = "nccl" if self.device == "cuda" else "gloo"
        if backend == "nccl":
            torch.cuda.set_device(0)
        dist.init_process_group(
            backend=backend,
            rank=self.rank,
            world_size=self.world_size,
            timeout=datetime.timedelta(seconds=timeout_s),
        )

    # -- time-sharing hooks (collocated mode) -------------------------------------------------
    def offload(self) -> None:
        """Free device memory so a collocated component can use the device. Default: nothing."""

    def reload(self) -> None:
        """Bring state back to the device after ``offload``. Default: nothing."""

    # -- introspection used by the runtime ----------------------------------------------------
    def _infinirl_where(self) -> dict:
        return {
            "component": self.component,
            "rank": self.rank,
            "node_ip": self.ctx.node_ip,
            "hostname": socket.gethostname(),
            "pid": os.getpid(),
        }


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


class _WorkerHost:
    """The Ray actor that hosts one ``Worker`` rank; turns every failure into a ``WorkerError``."""

    def __init__(self, worker_cls: type, ctx: RankContext, args: tuple, kwargs: dict):
        os.environ.update(ctx.env_vars)
        _quiet_ray_async_warnings()
        self._restarted = _was_reconstructed()
        self._ctx = ctx
        self._spans: list[tuple] = []
        self._sync_executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="infinirl-sync",
                                                 initializer=mark_compute_thread)
        self._sync_executor.submit(lambda: None)  # start the thread now: it is the compute thread from here on
        self._init_error: WorkerError | None = None
        self._next_seq: dict[str, int] = defaultdict(int)
        self._turn = asyncio.Condition()
        self._node_ip = ray.util.get_node_ip_address()
        ctx.node_ip = ctx.node_ip or self._node_ip
        self._crash_log = self._enable_crash_log(ctx)
        from infinirl.runtime import p2p

        p2p.register_host(ray.get_runtime_context().current_actor)
        try:
            # On the compute thread, like every sync method: the constructor builds models and
            # may run parallel torch ops, and one OpenMP team on a second thread makes libgomp
            # count more threads than cores and stop spin-waiting (0 turns under PASSIVE) for
            # every team in the process (see compute_thread): the pixels update 1.1-1.4x slower.
            self._worker = self._sync_executor.submit(_construct, worker_cls, ctx, args, kwargs).result()
        except BaseException:  # reported on the first call (see ready())
            self._worker = None
            self._init_error = self._error("__init__", traceback.format_exc())

    @staticmethod
    def _enable_crash_log(ctx: RankContext) -> str:
        """Hard crashes (segfault, abort) write their Python stacks here; the driver quotes it.

        One file per rank (``ctx.crash_log_name``), not per process: a rank that Ray restarts
        appends to it under a line naming the new process, so the driver quotes the crash of the
        process that died last (see :func:`_last_process_crash`), not the first one's."""
        CRASH_LOG_DIR.mkdir(parents=True, exist_ok=True)
        path = CRASH_LOG_DIR / (ctx.crash_log_name or f"{ctx.component}-rank{ctx.rank}-pid{os.getpid()}.log")
        handle = open(path, "a")  # kept open for the life of the process, as faulthandler needs
        handle.write(f"{_CRASH_LOG_PROCESS}{os.getpid()}\n")
        handle.flush()
        faulthandler.enable(file=handle, all_threads=True)
        return str(path)

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
        actors do not guarantee it); sync ones then run FIFO on the single executor thread."""
        if self._init_error is not None:
            raise self._init_error
        fn = getattr(self._worker, method)
        if seq >= 0:
            async with self._turn:
                if caller not in self._next_seq and self._restarted:
                    self._next_seq[caller] = seq  # a restarted rank resumes the caller's numbering
                await self._turn.wait_for(lambda: self._next_seq[caller] == seq)
        start = time.time()
        ok = False
        try:
            if inspect.iscoroutinefunction(fn):
                pending = asyncio.ensure_future(fn(*args, **kwargs))
            else:
                loop = asyncio.get_running_loop()
                pending = loop.run_in_executor(self._sync_executor, lambda: fn(*args, **kwargs))
        finally:
            if seq >= 0:
                async with self._turn:
                    self._next_seq[caller] = seq + 1
                    self._turn.notify_all()
        try:
            result = await pending
            ok = True
            return result
        except BaseException:
            raise self._error(method, traceback.format_exc()) from None
        finally:
            self._spans.append((self._ctx.component, self._ctx.rank, method, start, time.time(), ok))

    async def _infinirl_p2p_serve(self, item: int, key: tuple, addr: str, port: int, backend: str) -> int:
        """Send a p2p channel item to the consumer that pulls it (runs beside the worker's method)."""
        from infinirl.runtime import p2p

        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(p2p._comm, p2p.serve, item, key, addr, port, backend)

    async def _infinirl_p2p_release(self, item: int) -> None:
        from infinirl.runtime import p2p

        p2p.release(item)

    async def pop_spans(self) -> list[tuple]:
        spans, self._spans = self._spans, []
        return spans

    async def free_port(self) -> int:
        with socket.socket() as sock:
            sock.bind(("", 0))
            return sock.getsockname()[1]


class GroupHandle:
    """The pending result of one fan-out call: ``wait()``, ``await handle``, ``done()``.

    ``wait`` returns the per-rank results in rank order. It raises the first failure as soon as it
    happens (not after the other ranks finish), so one broken rank never looks like a hang.
    """

    def __init__(self, group: "WorkerGroup", method: str, ranks: list[int], refs: list):
        self._group = group
        self.method = method
        self.ranks = ranks
        self._refs = refs
        self._results: list | None = None

    def done(self) -> bool:
        if self._results is not None:
            return True
        ready, _ = ray.wait(self._refs, num_returns=len(self._refs), timeout=0)
        return len(ready) == len(self._refs)

    def wait(self, timeout: float | None = None) -> list:
        if self._results is not None:
            return self._results
        deadline = None if timeout is None else time.monotonic() + timeout
        pending = list(self._refs)
        while pending:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready, pending = ray.wait(pending, num_returns=1, timeout=remaining)
            if not ready:
                waiting = [self.ranks[self._refs.index(r)] for r in pending]
                raise TimeoutError(
                    f"{self._group.component}.{self.method}() not finished after {timeout}s on "
                    f"rank(s) {waiting}"
                )
            self._get(ready[0])  # raises the first failure right away
        self._results = [self._get(ref) for ref in self._refs]
        return self._results

    def _get(self, ref):
        rank = self.ranks[self._refs.index(ref)]
        return self._group._get_or_explain(ref, rank, self.method)

    def __await__(self):
        return self._await().__await__()

    async def _await(self) -> list:
        futures = {asyncio.ensure_future(_settle(ref)): ref for ref in self._refs}
        remaining = set(futures)
        while remaining:
            done, remaining = await asyncio.wait(remaining, return_when=asyncio.FIRST_COMPLETED)
            for fut in done:
                self._get(futures[fut])  # raises the first failure right away
        return self.wait()


async def _settle(ref) -> None:
    """Await a ref without raising: the failure is re-read (and explained) by ``_get``."""
    try:
        await ref
    except BaseException:
        pass


_LIVE_GROUPS: weakref.WeakSet = weakref.WeakSet()  # launched here and not shut down yet


def shutdown_all_groups() -> None:
    """Shut down every group this process launched and has not shut down. A ``Cluster`` that
    started Ray calls this before stopping it: Ray would kill the ranks anyway, but only the
    groups know which crash logs to remove (a program need not shut its groups down itself)."""
    for group in list(_LIVE_GROUPS):
        group.shutdown()


class WorkerGroup:
    """N ranks of one ``Worker`` class, launched as Ray actors; call methods on all of them at once."""

    def __init__(self, worker_cls: type, component: str, actors: list, contexts: list[RankContext]):
        self.worker_cls = worker_cls
        self.component = component
        self._actors = actors
        self.contexts = contexts
        self.rank_info: list[dict] = []
        self._caller = uuid.uuid4().hex
        self._seq = [0] * len(actors)
        # A group dropped without shutdown(): Ray ends its ranks once the last handle goes, and
        # this removes their crash logs then (or at exit) unless a crash was written to them.
        self._remove_crash_logs = weakref.finalize(
            self, _remove_all_if_no_crash,
            [str(CRASH_LOG_DIR / ctx.crash_log_name) for ctx in contexts if ctx.crash_log_name])

    # ------------------------------------------------------------------ launch
    @classmethod
    def launch(
        cls,
        worker_cls: type,
        component: str | None = None,
        num_ranks: int | None = None,
        placement: list | tuple | None = None,
        args: tuple = (),
        kwargs: dict | None = None,
        restart: RestartPolicy | None = None,
        env_vars: dict[str, str] | None = None,
        ready_timeout_s: float = 300.0,
    ) -> "WorkerGroup":
        """Start the ranks and wait until every one has constructed its Worker.

        ``placement`` is the tuple of ``RankPlacement`` that ``placement.place`` gives for this
        component; without it, ``num_ranks`` CPU ranks go wherever Ray puts them.

        ``env_vars`` are in every rank's environment from its process's start (Ray's runtime_env),
        not only set once the Worker is built: libraries that read their settings when they load
        (OpenMP's wait policy, when torch is imported) see them.
        """
        if not (isinstance(worker_cls, type) and issubclass(worker_cls, Worker)):
            raise TypeError(f"WorkerGroup.launch needs a Worker subclass, got {worker_cls!r}")
        component = component or worker_cls.__name__
        kwargs = kwargs or {}
        contexts = _contexts_for(component, num_ranks, placement, env_vars or {})
        master_addr, master_port = _pick_master(contexts[0])
        options = {"num_cpus": 0, "namespace": NAMESPACE, "max_concurrency": 1000}
        if restart is not None:
            options["max_restarts"] = restart.max_restarts
            options["max_task_retries"] = restart.max_restarts if restart.retry_calls else 0
        host_cls = ray.remote(_WorkerHost)
        actors = []
        for ctx in contexts:
            ctx.env_vars.update(
                {
                    "MASTER_ADDR": master_addr,
                    "MASTER_PORT": str(master_port),
                    "RANK": str(ctx.rank),
                    "WORLD_SIZE": str(ctx.world_size),
                }
            )
            ctx.env_vars.setdefault("LOCAL_RANK", "0")
            ctx.crash_log_name = f"{component}-rank{ctx.rank}-{uuid.uuid4().hex[:12]}.log"
            opts = dict(options, runtime_env={"env_vars": {**worker_env(), **(env_vars or {})}})
            if ctx.node_id:
                opts["scheduling_strategy"] = NodeAffinitySchedulingStrategy(ctx.node_id, soft=False)
            actors.append(host_cls.options(**opts).remote(worker_cls, ctx, args, kwargs))
        group = cls(worker_cls, component, actors, contexts)
        _LIVE_GROUPS.add(group)
        handle = GroupHandle(group, "__init__", list(range(len(actors))), [a.ready.remote() for a in actors])
        try:
            group.rank_info = handle.wait(timeout=ready_timeout_s)
        except BaseException:
            group.shutdown()
            raise
        return group

    # ------------------------------------------------------------------ calls
    @property
    def world_size(self) -> int:
        return len(self._actors)

    def call(self, method: str, *args, ranks: list[int] | None = None, **kwargs) -> GroupHandle:
        """Call ``method(*args, **kwargs)`` on the chosen ranks (default all); returns at once."""
        self._check_method(method)
        ranks = list(range(self.world_size)) if ranks is None else list(ranks)
        for rank in ranks:
            if not 0 <= rank < self.world_size:
                raise IndexError(
                    f"{self.component} has ranks 0-{self.world_size - 1}; rank {rank} does not exist"
                )
        refs = [self._submit(r, method, args, kwargs) for r in ranks]
        return GroupHandle(self, method, ranks, refs)

    def _submit(self, rank: int, method: str, args: tuple, kwargs: dict):
        seq = self._seq[rank]
        self._seq[rank] += 1
        return self._actors[rank].execute.remote(method, args, kwargs, self._caller, seq)

    def __getstate__(self):
        raise TypeError(
            "a WorkerGroup stays in the process that launched it; pass Channels to workers instead"
        )

    def call_each(self, method: str, per_rank_args: list[tuple], **kwargs) -> GroupHandle:
        """Call ``method`` on every rank with its own positional args (scatter)."""
        self._check_method(method)
        if len(per_rank_args) != self.world_size:
            raise ValueError(
                f"{self.component}.call_each: got {len(per_rank_args)} argument tuples for "
                f"{self.world_size} ranks"
            )
        refs = [self._submit(r, method, tuple(args), kwargs) for r, args in enumerate(per_rank_args)]
        return GroupHandle(self, method, list(range(self.world_size)), refs)

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        self._check_method(name)
        return lambda *args, **kwargs: self.call(name, *args, **kwargs)

    def _check_method(self, method: str) -> None:
        if callable(getattr(self.worker_cls, method, None)):
            return
        public = sorted(
            n for n, v in inspect.getmembers(self.worker_cls, callable)
            if not n.startswith("_") and not isinstance(getattr(Worker, n, None), property)
        )
        near = difflib.get_close_matches(method, public, n=1)
        hint = f" Did you mean '{near[0]}'?" if near else ""
        raise AttributeError(
            f"component '{self.component}' ({self.worker_cls.__name__}) has no method '{method}'.{hint} "
            f"Its methods: {', '.join(public)}"
        )

    def _get_or_explain(self, ref, rank: int, method: str):
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause if isinstance(getattr(exc, "cause", None), WorkerError) else None
            if cause is not None:
                raise cause from None
            raise self._died(rank, method, str(exc)) from None
        except ray.exceptions.RayActorError as exc:
            raise self._died(rank, method, str(exc)) from None

    def _died(self, rank: int, method: str, ray_message: str) -> WorkerError:
        info = self.rank_info[rank] if rank < len(self.rank_info) else {}
        crash_pid, crash = _last_process_crash(info.get("crash_log"))
        text = (crash + "\n" if crash else "") + _first_line_block(ray_message)
        return WorkerError(
            component=self.component,
            rank=rank,
            method=method,
            node_ip=info.get("node_ip", self.contexts[rank].node_ip or "?"),
            hostname=info.get("hostname", "?"),
            pid=crash_pid or info.get("pid"),
            traceback_text=text,
            cause="died (process exited)",
        )

    # ------------------------------------------------------------------ tracing / lifecycle
    def pop_spans(self) -> list[tuple]:
        """Per-call spans (component, rank, method, start, end, ok) recorded since the last pop."""
        spans = []
        for actor in self._actors:
            try:
                spans.extend(ray.get(actor.pop_spans.remote(), timeout=30))
            except Exception:
                pass  # a dead rank has no spans to give; its failure was already reported
        return spans

    def shutdown(self) -> None:
        """Kill every rank's process and remove its crash log if no crash was written to it (one
        file per rank otherwise piles up in the temp dir; a log with a crash in it is kept for
        the user). Idempotent."""
        for actor in self._actors:
            try:
                ray.kill(actor, no_restart=True)
            except Exception:
                pass
        self._actors = []
        _LIVE_GROUPS.discard(self)
        _remove_all_if_no_crash(info.get("crash_log") for info in self.rank_info)  # as each rank's node names it
        self._remove_crash_logs()  # by the names given at launch: also ranks that failed to start

    def pids(self) -> list[int]:
        return [info.get("pid") for info in self.rank_info]


def _remove_all_if_no_crash(paths) -> None:
    for path in paths:
        _remove_if_no_crash(path)


def _remove_if_no_crash(path: str | None) -> None:
    """Delete a crash log that holds nothing but its processes' start lines (a rank on another
    node: not visible here, skipped)."""
    if not path:
        return
    try:
        lines = Path(path).read_text(errors="replace").splitlines()
        if all(not line.strip() or line.startswith(_CRASH_LOG_PROCESS) for line in lines):
            os.unlink(path)
    except OSError:
        pass


def _contexts_for(component, num_ranks, placement, extra_env) -> list[RankContext]:
    if placement:
        if num_ranks is not None and num_ranks != len(placement):
            raise ValueError(
                f"{component}: num_ranks={num_ranks} but the placement has {len(placement)} ranks"
            )
        return [
            RankContext(
                component=component,
                rank=p.rank,
                world_size=p.world_size,
                node_id=p.node_id,
                node_ip=p.node_ip,
                local_devices=tuple(p.local_devices),
                cpu_slots=tuple(p.cpu_slots),
                robot=p.robot,
                env_vars={**p.env_vars, **extra_env},
            )
            for p in placement
        ]
    n = 1 if num_ranks is None else int(num_ranks)
    if n < 1:
        raise ValueError(f"{component}: num_ranks must be >= 1, got {num_ranks}")
    return [RankContext(component=component, rank=r, world_size=n, env_vars=dict(extra_env)) for r in range(n)]


def _free_port() -> tuple[str, int]:
    with socket.socket() as sock:
        sock.bind(("", 0))
        return ray.util.get_node_ip_address(), sock.getsockname()[1]


def _pick_master(rank0: RankContext) -> tuple[str, int]:
    """A free TCP port on rank 0's node, found *on that node*, for torch.distributed rendezvous.

    On this process's own node (or with no node asked for) the port is found here: a Ray task
    would need a worker process of its own, started (importing torch) for a microsecond's work,
    since a Cluster we start keeps no idle workers (``LOCAL_RAY_SYSTEM_CONFIG``)."""
    if rank0.node_id is None or rank0.node_id == ray.get_runtime_context().get_node_id():
        return _free_port()
    task = ray.remote(num_cpus=0)(_free_port).options(
        scheduling_strategy=NodeAffinitySchedulingStrategy(rank0.node_id, soft=False))
    return ray.get(task.remote())


def _last_process_crash(path: str | None, max_chars: int = 4000) -> tuple[int | None, str]:
    """(pid, crash text) of the last process that wrote to a rank's crash log: its section
    after its own ``_CRASH_LOG_PROCESS`` line, empty if that process wrote no crash."""
    if not path:
        return None, ""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return None, ""
    _, marker, last = text.rpartition(_CRASH_LOG_PROCESS)
    if not marker:
        return None, text.strip()[-max_chars:]
    pid_line, _, crash = last.partition("\n")
    return (int(pid_line) if pid_line.strip().isdigit() else None), crash.strip()[-max_chars:]


def _first_line_block(message: str, max_lines: int = 12) -> str:
    lines = [ln for ln in message.splitlines() if ln.strip()]
    return "\n".join(lines[:max_lines])
