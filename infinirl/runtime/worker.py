"""Worker and WorkerGroup: a component's ranks as Ray actors, with fan-out calls and clear failures.

A ``Worker`` subclass holds the logic of one component rank (an actor trainer, a rollout engine,
an env server...). ``WorkerGroup.launch`` starts one Ray actor per rank (a ``worker_host.WorkerHost``),
each with RANK/WORLD_SIZE/MASTER_ADDR/MASTER_PORT set so a torch.distributed group can form on
demand (``Worker.init_process_group``). ``group.method(...)`` fans a call out to all (or chosen)
ranks and returns a ``GroupHandle`` at once: ``wait()``, ``await``, ``done()``, ``cancel()``.

Execution inside a rank: synchronous methods run one at a time, in call order, on one dedicated
thread (so torch state and CUDA's per-thread device stay consistent); ``async def`` methods run
concurrently on the actor's event loop (e.g. a server loop next to a status query).

Failure reporting is the point of this module. An exception in any rank reaches the driver as one
``WorkerError`` naming component, rank, node, host, method and the original traceback, raised as
soon as the *first* rank fails (other ranks blocked in a collective would otherwise hang or fail
with a secondary error). A rank whose process died is reported with its crash log (``crash_logs``),
not as an opaque "actor died"; a result Ray could not serialise is reported as such, naming its type.
"""

from __future__ import annotations

import asyncio
import difflib
import inspect
import os
import socket
import sys
import threading
import time
import uuid
import weakref
from dataclasses import dataclass

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from infinirl.runtime import crash_logs, rendezvous
from infinirl.runtime.cancellation import cancel_quietly
from infinirl.runtime.crash_logs import CRASH_LOG_DIR
from infinirl.runtime.errors import CallCancelled, WorkerError
from infinirl.runtime.ray_defaults import NAMESPACE, worker_env
from infinirl.runtime.worker_host import RankContext, WorkerHost

# CRASH_LOG_DIR and RankContext are part of this module's interface (imported from here).
__all__ = ["CRASH_LOG_DIR", "GroupHandle", "RankContext", "RestartPolicy", "Worker", "WorkerGroup",
           "shutdown_all_groups"]


@dataclass(frozen=True)
class RestartPolicy:
    """For stateless components (env, reward): restart a dead rank up to ``max_restarts`` times.

    With ``retry_calls`` the call that was running when the process died is re-sent to the new
    process, so the driver sees a result instead of an error.
    """

    max_restarts: int = 3
    retry_calls: bool = True


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

    def _infinirl_accelerator_peak(self) -> float | None:
        """The most accelerator memory torch's allocator reserved in this process, in bytes (the
        scheduler's profiler reads it); 0 when the process never used CUDA through torch, None
        when it cannot be read. The CUDA context and other libraries' memory are not counted."""
        torch = sys.modules.get("torch")
        if torch is None:
            return 0.0
        try:
            if not torch.cuda.is_initialized():
                return 0.0
            return float(sum(torch.cuda.max_memory_reserved(d) for d in range(torch.cuda.device_count())))
        except Exception:
            return None


# A rank that dies in a collective makes its peers raise within milliseconds (gloo: "Connection
# closed by peer"), while Ray reports the death itself about a second later: a method's exception
# waits this long for a death among the call's other ranks, which is then reported as the cause.
PEER_DEATH_GRACE_S = 2.0


class GroupHandle:
    """The pending result of one fan-out call: ``wait()``, ``await handle``, ``done()``, ``cancel()``.

    ``wait`` returns the per-rank results in rank order. It raises the first failure as soon as it
    happens (not after the other ranks finish), so one broken rank never looks like a hang;
    ``wait(timeout=)`` raises ``TimeoutError`` naming the method and the ranks still running.
    A method's exception is held up to ``PEER_DEATH_GRACE_S`` while the call runs on other ranks:
    if one of them died meanwhile, that death (the root cause, with its crash log) is raised,
    chained to the exception.
    """

    def __init__(self, group: "WorkerGroup", method: str, ranks: list[int], refs: list,
                 seqs: list[int] | None = None):
        self._group = group
        self.method = method
        self.ranks = ranks
        self._refs = refs
        self._seqs = seqs if seqs is not None else [-1] * len(refs)
        self._results: list | None = None

    def done(self) -> bool:
        """True once every rank has finished the call (returned, failed or been cancelled)."""
        if self._results is not None:
            return True
        ready, _ = ray.wait(self._refs, num_returns=len(self._refs), timeout=0)
        return len(ready) == len(self._refs)

    def cancel(self) -> None:
        """Cancel the call on every rank that has not finished it. A call still waiting for its
        turn never runs, so later calls to the group do not wait behind it; an ``async def``
        method is cancelled where it awaits; a synchronous method waiting in a ``Channel`` call
        stops with ``CallCancelled`` and frees the rank for its next call, while one that
        computes (or blocks elsewhere) runs to its end first. ``wait()`` then raises
        ``CallCancelled`` for a rank whose call was cancelled."""
        for ref, rank, seq in zip(self._refs, self.ranks, self._seqs):
            cancel_quietly(ref)
            self._group._skip(rank, seq)  # a call Ray cancels before it reaches the rank

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
            try:
                self._get(ready[0])  # raises the first failure right away...
            except WorkerError as raised:
                self._raise_a_death_behind(raised, pending)  # ...unless a rank's death caused it
                raise
        self._results = [self._get(ref) for ref in self._refs]
        return self._results

    def _raise_a_death_behind(self, raised: WorkerError, others: list) -> None:
        """``raised`` came first; if one of the ``others`` turns out dead within
        ``PEER_DEATH_GRACE_S``, raise that death (with its crash log), chained to ``raised``."""
        if raised.cause != "raised":
            return
        deadline = time.monotonic() + PEER_DEATH_GRACE_S
        while others:
            ready, others = ray.wait(others, num_returns=1, timeout=max(0.0, deadline - time.monotonic()))
            if not ready:
                return
            died = self._death_of(ready[0])
            if died is not None:
                raise died from raised

    def _death_of(self, ref) -> WorkerError | None:
        """The ``died`` error of a finished ref whose rank's process died, else None."""
        try:
            ray.get(ref, timeout=0)
        except ray.exceptions.RayActorError as exc:
            index = self._refs.index(ref)
            return self._group._died(self.ranks[index], self.method, str(exc))
        except Exception:  # returned, raised or cancelled: not a death
            pass
        return None

    def _get(self, ref):
        index = self._refs.index(ref)
        return self._group._get_or_explain(ref, self.ranks[index], self.method, self._seqs[index])

    def __await__(self):
        return self._await().__await__()

    async def _await(self) -> list:
        futures = {asyncio.ensure_future(_settle(ref)): ref for ref in self._refs}
        remaining = set(futures)
        while remaining:
            done, remaining = await asyncio.wait(remaining, return_when=asyncio.FIRST_COMPLETED)
            for fut in done:
                try:
                    self._get(futures[fut])  # raises the first failure right away...
                except WorkerError as raised:  # ...unless a rank's death caused it (see wait)
                    await self._raise_a_death_behind_async(raised, futures, (done | remaining) - {fut})
                    raise
        return self.wait()

    async def _raise_a_death_behind_async(self, raised: WorkerError, futures: dict, others: set) -> None:
        if raised.cause != "raised":
            return
        deadline = time.monotonic() + PEER_DEATH_GRACE_S
        while others:
            finished, others = await asyncio.wait(others, timeout=max(0.0, deadline - time.monotonic()),
                                                  return_when=asyncio.FIRST_COMPLETED)
            if not finished:
                return
            for fut in finished:
                died = self._death_of(futures[fut])
                if died is not None:
                    raise died from raised


async def _settle(ref) -> None:
    """Await a ref without raising: the failure is re-read (and explained) by ``_get``."""
    try:
        await ref
    except BaseException:
        pass


class _TurnKeeper:
    """Gives up the turn, in its rank's call order, of a call that Ray failed before it ran.

    Ray can fail a call before ``WorkerHost.execute`` starts (an argument the rank cannot
    unpickle, e.g. an instance of a class only the driver can import): the call never takes its
    turn, and every later call to that rank would wait for it, whether or not anyone waits on the
    failed call's handle. One thread per driver process watches each numbered call until it
    finishes and tells the rank to skip one that failed outside the method. Skipping a call that
    did take its turn does nothing (``CallOrder.skip``), so the check need not be exact."""

    _POLL_S = 0.5  # how soon a call submitted while the thread waits is watched too

    def __init__(self):
        self._lock = threading.Lock()
        # ObjectRef -> (weak ref to the rank's actor handle, caller, seq): a strong one would keep
        # the ranks of a group dropped without shutdown() alive as long as a call of theirs runs
        self._calls: dict = {}
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None

    def watch(self, ref, actor, caller: str, seq: int) -> None:
        with self._lock:
            self._calls[ref] = (weakref.ref(actor), caller, seq)
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="infinirl-call-turns", daemon=True)
                self._thread.start()
        self._wake.set()

    def _run(self) -> None:
        while True:
            self._wake.clear()
            with self._lock:
                idle = not self._calls
            if idle:
                self._wake.wait()
            else:
                self._check_once()

    def _check_once(self) -> None:
        """Waits up to ``_POLL_S`` for watched calls to finish, and skips the turns of those that
        failed outside their method. It holds the refs and actor handles only while it runs."""
        with self._lock:
            refs = list(self._calls)
        try:
            # fetch_local=False: a finished call's result stays where it is until it is asked for
            ready, _ = ray.wait(refs, num_returns=1, timeout=self._POLL_S, fetch_local=False)
            if ready:
                ready, _ = ray.wait(refs, num_returns=len(refs), timeout=0, fetch_local=False)
        except Exception:  # Ray was shut down: these calls are gone with their ranks
            ready = refs
        for ref in ready:
            with self._lock:
                actor_ref, caller, seq = self._calls.pop(ref)
            actor = actor_ref()
            if actor is not None and _failed_outside_the_method(ref):
                try:
                    actor.skip_call.remote(caller, seq)
                except Exception:  # the rank (or Ray) is gone: nothing waits there
                    pass


def _failed_outside_the_method(ref) -> bool:
    """Whether a finished call failed in Ray rather than in the method (a ``WorkerError``) or by
    its rank's death or a cancel. Only the driver's in-process store is read: errors are kept
    there, while a large result is in the object store and stays unfetched."""
    try:
        core_worker = ray._private.worker.global_worker.core_worker
        if not core_worker.object_exists(ref, memory_store_only=True):
            return False
    except Exception:  # no such internal API in this Ray: read the result
        pass
    try:
        ray.get(ref, timeout=0)
    except ray.exceptions.RayTaskError as exc:
        return not isinstance(getattr(exc, "cause", None), WorkerError)
    except (ray.exceptions.RayActorError, ray.exceptions.TaskCancelledError):
        return False
    except Exception:  # Ray could not run or answer it
        return True
    return False


_TURNS = _TurnKeeper()

_LIVE_GROUPS: weakref.WeakSet = weakref.WeakSet()  # launched here and not shut down yet
_names_lock = threading.Lock()
_names_in_use: set[str] = set()  # component names of the groups launched here and not gone


def shutdown_all_groups() -> None:
    """Shut down every group this process launched and has not shut down. A ``Cluster`` that
    started Ray calls this before stopping it: Ray would kill the ranks anyway, but only the
    groups know which crash logs to remove (a program need not shut its groups down itself)."""
    for group in list(_LIVE_GROUPS):
        group.shutdown()


def _claim_name(component: str) -> None:
    with _names_lock:
        if component in _names_in_use:
            raise ValueError(
                f"a WorkerGroup named '{component}' is already running in this process; shut it down "
                f"first, or launch this one under another component name"
            )
        _names_in_use.add(component)


def _forget_group(component: str, crash_log_paths: list[str], rendezvous_key: str = "") -> None:
    """A group is gone (shut down, or dropped and collected): free its name, remove its ranks'
    crash logs that hold no crash, and its published rendezvous."""
    with _names_lock:
        _names_in_use.discard(component)
    crash_logs.remove_if_no_crash(crash_log_paths)
    if rendezvous_key:
        rendezvous.forget(rendezvous_key)


class WorkerGroup:
    """N ranks of one ``Worker`` class, launched as Ray actors; call methods on all of them at once.

    A component name belongs to one live group per launching process: a second launch under the
    same name is refused until the first group is shut down (or dropped)."""

    def __init__(self, worker_cls: type, component: str, actors: list, contexts: list[RankContext]):
        self.worker_cls = worker_cls
        self.component = component
        self._actors = actors
        self.contexts = contexts
        self.rank_info: list[dict] = []
        self._caller = uuid.uuid4().hex
        self._seq = [0] * len(actors)
        # Driver threads sharing the group take call numbers under it: two calls with the same
        # number would leave a later one unused, and the rank would hold every call behind it for good.
        self._seq_lock = threading.Lock()
        self._launch_settings: tuple = ((), {}, None, {})  # args, kwargs, restart, env_vars: for resize()
        # A group dropped without shutdown(): Ray ends its ranks once the last handle goes, and
        # this frees its name and removes its crash logs then (or at exit) unless a crash was
        # written to them. The list grows with the ranks resize() adds.
        self._crash_log_paths = [str(CRASH_LOG_DIR / ctx.crash_log_name) for ctx in contexts if ctx.crash_log_name]
        self._forget = weakref.finalize(self, _forget_group, component, self._crash_log_paths,
                                        contexts[0].rendezvous_key if contexts else "")

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

        Also removes the crash logs that launches from processes now gone (e.g. a driver killed
        with SIGKILL) left on this host (``crash_logs.remove_orphaned``).
        """
        if not (isinstance(worker_cls, type) and issubclass(worker_cls, Worker)):
            raise TypeError(f"WorkerGroup.launch needs a Worker subclass, got {worker_cls!r}")
        component = component or worker_cls.__name__
        contexts = _contexts_for(component, num_ranks, placement, env_vars or {})
        crash_logs.remove_orphaned()
        _claim_name(component)
        key = rendezvous.new_key(component)
        try:
            actors = _start_hosts(worker_cls, contexts, args, kwargs or {}, restart, env_vars or {}, key)
        except BaseException:
            _forget_group(component, [], key)
            raise
        group = cls(worker_cls, component, actors, contexts)
        group._launch_settings = (args, kwargs or {}, restart, env_vars or {})
        _LIVE_GROUPS.add(group)
        handle = GroupHandle(group, "__init__", list(range(len(actors))), [a.ready.remote() for a in actors])
        try:
            group.rank_info = handle.wait(timeout=ready_timeout_s)
        except BaseException:
            group.shutdown()
            raise
        return group

    # ------------------------------------------------------------------ online scaling
    def resize(self, num_ranks: int, placement: list | tuple | None = None,
               ready_timeout_s: float = 300.0) -> None:
        """Grow or shrink the group to ``num_ranks`` while it runs, keeping ranks ``0..min-1`` as they are.

        Growing starts ranks ``world_size..num_ranks-1`` with the constructor arguments, restart
        policy and environment of the launch, where ``placement`` (the component's placement for
        ``num_ranks`` ranks, see :func:`~infinirl.runtime.placement.resized_spec`) puts them,
        and waits until each has built its Worker; a rank that fails to start is stopped and its
        error raised, leaving the group as it was. Shrinking stops the highest ranks (their
        pending calls fail). The caller hands work to the new ranks and stops giving it to the
        removed ones: a resize moves no state.

        For components whose ranks work independently (env servers, reward): ranks started
        later see the new ``world_size``, earlier ones keep the one they started with, and no
        torch.distributed group is re-formed."""
        if isinstance(num_ranks, bool) or not isinstance(num_ranks, int) or num_ranks < 1:
            raise ValueError(f"{self.component}.resize: num_ranks must be an int >= 1, got {num_ranks!r}")
        if placement is not None and len(placement) != num_ranks:
            raise ValueError(f"{self.component}.resize: placement has {len(placement)} ranks for num_ranks={num_ranks}")
        if not self._actors:
            raise RuntimeError(f"{self.component}.resize: the group was shut down")
        old = self.world_size
        if num_ranks < old:
            self._remove_ranks(num_ranks)
        elif num_ranks > old:
            self._add_ranks(num_ranks, placement, ready_timeout_s)

    def _add_ranks(self, num_ranks: int, placement, ready_timeout_s: float) -> None:
        args, kwargs, restart, env_vars = self._launch_settings
        old = self.world_size
        new = _contexts_for(self.component, num_ranks, placement, env_vars)[old:]
        actors = _start_hosts(self.worker_cls, new, args, kwargs, restart, env_vars, self.contexts[0].rendezvous_key)
        self._crash_log_paths.extend(str(CRASH_LOG_DIR / ctx.crash_log_name) for ctx in new)
        refs = [actor.ready.remote() for actor in actors]
        self._actors.extend(actors)
        self.contexts.extend(new)
        self._seq.extend([0] * len(actors))
        try:
            infos = GroupHandle(self, "__init__", list(range(old, num_ranks)), refs).wait(timeout=ready_timeout_s)
        except BaseException:
            self.rank_info.extend({} for _ in actors)
            self._remove_ranks(old)
            raise
        self.rank_info.extend(infos)

    def _remove_ranks(self, keep: int) -> None:
        for actor in self._actors[keep:]:
            try:
                ray.kill(actor, no_restart=True)
            except Exception:
                pass
        crash_logs.remove_if_no_crash(info.get("crash_log") for info in self.rank_info[keep:] if info)
        del self._actors[keep:], self.contexts[keep:], self._seq[keep:], self.rank_info[keep:]

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
        return self._submit_all(method, [(r, args) for r in ranks], kwargs)

    def _submit_all(self, method: str, calls: list[tuple[int, tuple]], kwargs: dict) -> GroupHandle:
        refs, seqs = [], []
        for rank, args in calls:
            actor = self._actors[rank]
            with self._seq_lock:
                seq = self._seq[rank]
                self._seq[rank] += 1
                try:
                    ref = actor.execute.remote(method, args, kwargs, self._caller, seq)
                except BaseException:  # e.g. an argument that cannot be pickled: the number is never used
                    self._skip(rank, seq)
                    raise
            _TURNS.watch(ref, actor, self._caller, seq)
            refs.append(ref)
            seqs.append(seq)
        return GroupHandle(self, method, [rank for rank, _ in calls], refs, seqs)

    def _skip(self, rank: int, seq: int) -> None:
        """Tell ``rank`` that call ``seq`` will not run, so its later calls do not wait for it."""
        if seq < 0:
            return
        try:
            self._actors[rank].skip_call.remote(self._caller, seq)
        except Exception:  # the rank is gone: nothing waits there
            pass

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
        return self._submit_all(method, [(r, tuple(args)) for r, args in enumerate(per_rank_args)], kwargs)

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

    def _get_or_explain(self, ref, rank: int, method: str, seq: int = -1):
        try:
            return ray.get(ref)
        except ray.exceptions.TaskCancelledError:
            raise CallCancelled(f"{self.component}[rank {rank}].{method}() was cancelled") from None
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, WorkerError):
                raise cause from None
            # Not the method (its errors are WorkerErrors) and not a dead process (RayActorError):
            # Ray failed around the call, e.g. to serialise what the method returned.
            raise self._not_delivered(rank, method, seq, exc) from None
        except ray.exceptions.RayActorError as exc:
            raise self._died(rank, method, str(exc)) from None

    def _not_delivered(self, rank: int, method: str, seq: int, exc: ray.exceptions.RayTaskError) -> WorkerError:
        try:
            returned = ray.get(self._actors[rank].returned_type.remote(self._caller, seq), timeout=30)
        except Exception:  # the rank is gone after all
            return self._died(rank, method, str(exc))
        cause = getattr(exc, "cause", None)
        reason = f"{type(cause).__name__}: {cause}" if cause is not None else _first_line_block(str(exc))
        if returned:
            what = (f"returned a value of type {returned} that could not be serialised to send back "
                    f"({reason}); the rank is alive and takes further calls")
        else:
            self._skip(rank, seq)  # it never started: later calls must not wait for its turn
            what = f"could not be run or answered by Ray ({reason}); the rank is alive"
        return self._error(rank, method, _first_line_block(str(exc)), what)

    def _died(self, rank: int, method: str, ray_message: str) -> WorkerError:
        info = self.rank_info[rank] if rank < len(self.rank_info) else {}
        ctx = self.contexts[rank] if rank < len(self.contexts) else None
        # Died before it reported (in its Worker's constructor): the log has the name launch gave
        # it, in the crash-log folder of the node placement chose (read there, see read_on_node).
        log = info.get("crash_log") or (ctx.crash_log_name if ctx else None)
        node_id = info.get("node_id") or (ctx.node_id if ctx else None)
        cause = "died (process exited)"
        try:
            crash_pid, crash = crash_logs.read_on_node(log, node_id)
        except crash_logs.CrashLogUnreadable as exc:
            crash_pid, crash = None, f"(no crash log: {exc})"
            if exc.node_gone:
                cause = "died (its node left the Ray cluster)"
        text = (crash + "\n" if crash else "") + _first_line_block(ray_message)
        return self._error(rank, method, text, cause, pid=crash_pid)

    def _error(self, rank: int, method: str, text: str, cause: str, pid: int | None = None) -> WorkerError:
        """A WorkerError for ``rank`` with what the group knows of the rank's host and process."""
        info = self.rank_info[rank] if rank < len(self.rank_info) else {}
        return WorkerError(
            component=self.component,
            rank=rank,
            method=method,
            node_ip=info.get("node_ip", self.contexts[rank].node_ip or "?"),
            hostname=info.get("hostname", "?"),
            pid=pid or info.get("pid"),
            traceback_text=text,
            cause=cause,
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
        """Kill every rank's process, free the component name, and remove each rank's crash log
        if no crash was written to it (one file per rank otherwise piles up in the temp dir; a
        log with a crash in it is kept for the user). Idempotent."""
        for actor in self._actors:
            try:
                ray.kill(actor, no_restart=True)
            except Exception:
                pass
        self._actors = []
        _LIVE_GROUPS.discard(self)
        crash_logs.remove_if_no_crash(info.get("crash_log") for info in self.rank_info)  # as each node names it
        self._forget()  # by the names given at launch: also ranks that failed to start

    def pids(self) -> list[int]:
        return [info.get("pid") for info in self.rank_info]


def _start_hosts(worker_cls: type, contexts: list[RankContext], args: tuple, kwargs: dict,
                 restart: RestartPolicy | None, env_vars: dict[str, str], rendezvous_key: str) -> list:
    """One ``WorkerHost`` actor per rank, all at once. Each finds the group's torch.distributed
    rendezvous under ``rendezvous_key`` (rank 0 binds and publishes it, see ``rendezvous``) and
    has it in its environment (MASTER_ADDR/MASTER_PORT) before its Worker is built."""
    options = {"num_cpus": 0, "namespace": NAMESPACE, "max_concurrency": 1000}
    if restart is not None:
        options["max_restarts"] = restart.max_restarts
        options["max_task_retries"] = restart.max_restarts if restart.retry_calls else 0
    host_cls = ray.remote(WorkerHost)
    actors = []
    for ctx in contexts:
        ctx.env_vars.update({"RANK": str(ctx.rank), "WORLD_SIZE": str(ctx.world_size)})
        ctx.env_vars.setdefault("LOCAL_RANK", "0")
        ctx.rendezvous_key = rendezvous_key
        ctx.crash_log_name = crash_logs.log_name(ctx.component, ctx.rank)
        opts = dict(options, runtime_env={"env_vars": {**worker_env(), **env_vars}})
        if ctx.node_id:
            opts["scheduling_strategy"] = NodeAffinitySchedulingStrategy(ctx.node_id, soft=False)
        actors.append(host_cls.options(**opts).remote(worker_cls, ctx, args, kwargs))
    return actors


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


def _first_line_block(message: str, max_lines: int = 12) -> str:
    lines = [ln for ln in message.splitlines() if ln.strip()]
    return "\n".join(lines[:max_lines])
