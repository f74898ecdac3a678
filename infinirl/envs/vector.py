"""The one vectoriser: ``num_envs`` sub-environments in worker processes, batched as an :class:`Env`.

Every CPU simulator (MetaWorld, gymnasium, ManiSkill on CPU, LIBERO) goes through this class; an
adapter only supplies a picklable factory ``factory(env_index) -> SubEnv``. What lives here, once:

* **Processes.** ``num_workers`` processes (``spawn`` context by default: forking a process that
  holds torch threads or a GL context is unsafe), each owning a contiguous block of sub-envs, so
  the cost of a message is paid per worker, not per env. ``num_workers=0`` steps the sub-envs in
  the calling process through the same code path (cheapest for tiny envs, and easy to debug).
  Observations travel pickled through pipes: simpler than shared memory and, measured, not the
  bottleneck for state or small RGB observations.
* **Auto-reset.** An env whose episode ends is reset at once; its last observation goes to
  ``info["final_obs"]``. Each env draws its episode seeds from its own stream, so a run is
  reproducible from ``seed`` alone, and envs reset to the same ``state_id`` stay in lockstep.
  ``step(..., autoreset=False)`` skips that reset for a step whose next observation nobody will
  use (a rollout's last step, before the next iteration resets every env with its own seed): a
  MetaWorld reset costs as much as ~40 steps. Such an env stays ended until ``reset``.
* **Crash recovery.** A sub-env whose ``step`` raises is rebuilt from its factory inside its
  worker; a worker process that dies (segfault, ``os._exit``, OOM kill) or exceeds
  ``step_timeout_s`` is replaced. Either way the affected episodes are reported truncated with
  ``info["restarted"]`` and training goes on; only a sub-env that cannot be rebuilt, or more than
  ``max_restarts`` crashes, stops the run, with the original traceback in the error.
* **Episode statistics.** Return, length and success-at-any-step are tracked here, in the parent,
  so they survive a worker that dies.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import traceback
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from infinirl.envs.base import (
    ActionSpace,
    EnvCrashError,
    Obs,
    ObservationSpec,
    StepResult,
    SubEnv,
    collate_obs,
    copy_obs,
    obs_row,
    set_obs_rows,
)

__all__ = ["SubEnvFactory", "VectorEnv"]

logger = logging.getLogger(__name__)

SubEnvFactory = Callable[[int], SubEnv]
"""Builds the sub-env with the given global index; must be picklable (a module-level class or a
``functools.partial`` of one) because worker processes call it."""

# Distinct seed-stream namespaces, so "seed 3" and "state 3" give different episode sequences.
_SEED_STREAM = 0
_STATE_STREAM = 1
_CLOSE_TIMEOUT_S = 5.0


# --------------------------------------------------------------------------------------------
# Inside a worker: sub-envs with seeds, time limits, auto-reset and in-place restarts.
# --------------------------------------------------------------------------------------------


@dataclass
class _SlotStep:
    """One sub-env's step as a worker reports it (pickled back to the parent)."""

    obs: Obs
    reward: float
    terminated: bool
    truncated: bool
    success: bool
    final_obs: Obs | None = None  # set when the episode ended and ``obs`` is a fresh reset
    restart_error: str | None = None  # set when the sub-env crashed and was rebuilt


@dataclass
class _BlockStep:
    """The steps of the envs one worker stepped, batched in the worker so that one small message
    (a few arrays) crosses the pipe instead of one object per env. Positions index the block."""

    obs: Obs
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    success: np.ndarray
    final_obs: dict[int, Obs]
    restart_errors: dict[int, str]

    @classmethod
    def from_slots(cls, steps: Sequence[_SlotStep]) -> _BlockStep:
        return cls(
            obs=collate_obs([step.obs for step in steps]),
            reward=np.array([step.reward for step in steps], dtype=np.float32),
            terminated=np.array([step.terminated for step in steps], dtype=bool),
            truncated=np.array([step.truncated for step in steps], dtype=bool),
            success=np.array([step.success for step in steps], dtype=bool),
            final_obs={k: step.final_obs for k, step in enumerate(steps) if step.final_obs is not None},
            restart_errors={
                k: step.restart_error for k, step in enumerate(steps) if step.restart_error is not None
            },
        )


class _EpisodeSlot:
    """One sub-env plus what every simulator needs around it: its episode-seed stream, the time
    limit, auto-reset, and rebuilding it from its factory when it raises."""

    def __init__(
        self,
        index: int,
        factory: SubEnvFactory,
        seed_entropy: Sequence[int],
        max_episode_steps: int | None,
    ) -> None:
        self.index = index
        self._factory = factory
        self._max_episode_steps = max_episode_steps
        self._seed_stream = np.random.default_rng(list(seed_entropy))
        self._length = 0
        self.env = factory(index)

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs:
        """Start an episode: at ``state_id`` if given, else with ``seed`` (else the next seed of
        this env's stream). Later auto-resets continue a stream derived from that seed or state,
        so envs reset to the same state keep starting identical episodes."""
        if state_id is not None:
            self._seed_stream = np.random.default_rng([state_id, _STATE_STREAM])
        elif seed is not None:
            self._seed_stream = np.random.default_rng([seed, _SEED_STREAM])
        else:
            seed = self._next_seed()
        return self._reset_or_rebuild(seed, state_id)

    def step(self, action: np.ndarray, autoreset: bool = True) -> _SlotStep:
        try:
            sub = self.env.step(action)
        except Exception:  # a crashing simulator must not take the run down
            error = traceback.format_exc()
            return _SlotStep(self._rebuild(error), 0.0, False, True, False, restart_error=error)
        self._length += 1
        out_of_time = self._max_episode_steps is not None and self._length >= self._max_episode_steps
        result = _SlotStep(
            sub.obs,
            float(sub.reward),
            bool(sub.terminated),
            bool(sub.truncated) or (out_of_time and not sub.terminated),
            bool(sub.success),
        )
        if result.terminated or result.truncated:
            result.final_obs = sub.obs
            if autoreset:
                result.obs = self._reset_or_rebuild(self._next_seed(), None)
        return result

    def _next_seed(self) -> int:
        return int(self._seed_stream.integers(2**31 - 1))

    def _reset_or_rebuild(self, seed: int | None, state_id: int | None) -> Obs:
        self._length = 0
        try:
            return self.env.reset(seed=seed, state_id=state_id)
        except Exception:
            error = traceback.format_exc()
        logger.warning("sub-env %d failed to reset; rebuilding it:\n%s", self.index, error)
        self._replace_env(error)
        try:
            return self.env.reset(seed=seed, state_id=state_id)
        except Exception as exc:
            raise EnvCrashError(
                f"sub-env {self.index} fails to reset even when freshly built:\n"
                f"{traceback.format_exc()}\nfirst failure:\n{error}"
            ) from exc

    def _rebuild(self, error: str) -> Obs:
        """Replace a crashed sub-env and start it on the next seed of its stream."""
        self._replace_env(error)
        return self._reset_or_rebuild(self._next_seed(), None)

    def _replace_env(self, error: str) -> None:
        try:
            self.env.close()
        except Exception:  # the old env is broken anyway; closing it is best effort
            pass
        try:
            self.env = self._factory(self.index)
        except Exception as exc:
            raise EnvCrashError(
                f"sub-env {self.index} crashed and cannot be rebuilt:\n{traceback.format_exc()}\n"
                f"original crash:\n{error}"
            ) from exc

    def close(self) -> None:
        self.env.close()


class _SlotGroup:
    """The sub-envs one worker owns, answering the parent's commands. Local slot ``k`` is global
    env ``indices[k]``; ``generation`` counts process restarts so a replacement worker draws
    episode seeds different from the ones its dead predecessor used."""

    def __init__(
        self,
        factory: SubEnvFactory,
        indices: Sequence[int],
        base_seed: int,
        generation: int,
        max_episode_steps: int | None,
    ) -> None:
        self.slots = [
            _EpisodeSlot(index, factory, (base_seed, index, generation), max_episode_steps)
            for index in indices
        ]

    def specs(self) -> tuple[ActionSpace, dict]:
        env = self.slots[0].env
        return env.action_space, dict(env.observation_spec)

    def reset(self, requests: Sequence[tuple[int, int | None, int | None]]) -> Obs:
        """``requests``: (local slot, seed, state_id) per env to reset; batched first obs."""
        return collate_obs([self.slots[k].reset(seed, state_id) for k, seed, state_id in requests])

    def step(self, slots: Sequence[int], actions: np.ndarray, autoreset: bool = True) -> _BlockStep | None:
        """Step local ``slots`` with the matching rows of ``actions``."""
        if not slots:
            return None
        return _BlockStep.from_slots([self.slots[k].step(a, autoreset) for k, a in zip(slots, actions, strict=False)])

    def render(self) -> list[np.ndarray]:
        return [slot.env.render() for slot in self.slots]

    def close(self) -> None:
        for slot in self.slots:
            slot.close()


_COMMANDS: dict[str, Callable[..., Any]] = {
    "reset": _SlotGroup.reset,
    "step": _SlotGroup.step,
    "render": _SlotGroup.render,
    "close": _SlotGroup.close,
}


def _worker_main(conn, factory, indices, base_seed, generation, max_episode_steps) -> None:
    """Entry point of a worker process: build the slots, then serve commands until told to close
    or until the parent disappears (its end of the pipe closes)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    try:
        group = _SlotGroup(factory, indices, base_seed, generation, max_episode_steps)
        conn.send(("ok", group.specs()))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
        conn.close()
        return
    while True:
        try:
            command, args = conn.recv()
        except (EOFError, OSError):
            break
        try:
            reply = ("ok", _COMMANDS[command](group, *args))
        except Exception:
            reply = ("error", traceback.format_exc())
        conn.send(reply)
        if command == "close":
            break
    conn.close()


# --------------------------------------------------------------------------------------------
# In the parent: one handle per worker, in-process or a child process, with one interface.
# --------------------------------------------------------------------------------------------


class _WorkerLost(Exception):
    """The worker process died or stopped answering; the parent replaces it."""


class _LocalWorker:
    """Runs a :class:`_SlotGroup` in the calling process (``num_workers=0``)."""

    def __init__(self, factory, indices, base_seed, max_episode_steps) -> None:
        self.indices = list(indices)
        self._group = _SlotGroup(factory, indices, base_seed, 0, max_episode_steps)
        self.specs = self._group.specs()
        self._pending: tuple[str, tuple] | None = None

    def send(self, command: str, *args: Any) -> None:
        self._pending = (command, args)

    def receive(self, timeout_s: float | None = None) -> Any:
        command, args = self._pending
        self._pending = None
        return _COMMANDS[command](self._group, *args)

    def restart(self) -> None:  # a local worker cannot die without taking the parent with it
        raise AssertionError("in-process workers are never restarted")

    def close(self) -> None:
        self._group.close()


class _ProcessWorker:
    """A child process owning ``indices``; ``receive`` turns death or silence into
    :class:`_WorkerLost` and a Python error inside it into :class:`EnvCrashError`."""

    def __init__(self, context, factory, indices, base_seed, max_episode_steps) -> None:
        self.indices = list(indices)
        self._context = context
        self._args = (factory, self.indices, base_seed)
        self._max_episode_steps = max_episode_steps
        self.generation = 0
        self.process = None
        self._conn = None
        self.specs = None

    def start(self) -> None:
        parent_conn, child_conn = self._context.Pipe()
        factory, indices, base_seed = self._args
        self.process = self._context.Process(
            target=_worker_main,
            args=(child_conn, factory, indices, base_seed, self.generation, self._max_episode_steps),
            name=f"infinirl-env-worker-{indices[0]}-{indices[-1]}",
            daemon=True,
        )
        self.process.start()
        child_conn.close()  # so that the child's death reads as EOF here
        self._conn = parent_conn

    def wait_ready(self) -> None:
        self.specs = self.receive()

    def send(self, command: str, *args: Any) -> None:
        try:
            self._conn.send((command, args))
        except (BrokenPipeError, OSError):
            pass  # the death is reported by the following receive

    def receive(self, timeout_s: float | None = None) -> Any:
        try:
            if not self._conn.poll(timeout_s):
                raise _WorkerLost(f"no answer within {timeout_s} s")
            status, payload = self._conn.recv()
        except (EOFError, OSError, ConnectionError) as exc:
            self.process.join(_CLOSE_TIMEOUT_S)  # reap it, so the exit code is known
            raise _WorkerLost(f"process died (exit code {self.process.exitcode})") from exc
        if status == "error":
            raise EnvCrashError(f"sub-envs {self.indices} failed in their worker process:\n{payload}")
        return payload

    def restart(self) -> None:
        self._stop(graceful=False)
        self.generation += 1
        self.start()
        self.wait_ready()

    def close(self) -> None:
        self._stop(graceful=True)

    def _stop(self, graceful: bool) -> None:
        if self.process is None:
            return
        if graceful and self.process.is_alive():
            self.send("close")
            try:
                self.receive(_CLOSE_TIMEOUT_S)
            except (_WorkerLost, EnvCrashError):
                pass
            self.process.join(_CLOSE_TIMEOUT_S)
        if self.process.is_alive():
            self.process.kill()
        self.process.join()  # reaps the child: no zombie left behind
        self._conn.close()
        self.process = None


def _close_workers(workers: list) -> None:
    for worker in workers:
        try:
            worker.close()
        except Exception:  # closing is best effort; one broken worker must not keep others open
            logger.exception("closing env worker %s failed", worker.indices)


class VectorEnv:
    """``num_envs`` copies of a :class:`SubEnv` stepped as one batched :class:`Env`.

    Args:
        factory: ``factory(env_index) -> SubEnv``, picklable (see :data:`SubEnvFactory`).
        num_envs: how many sub-envs.
        num_workers: worker processes; the envs are split into contiguous blocks among them.
            ``0`` runs everything in this process. Default: one per CPU core, at most ``num_envs``.
        seed: base seed; env ``i`` draws its episode seeds from a stream seeded by ``(seed, i)``.
        max_episode_steps: truncate episodes after this many steps (on top of any limit the
            simulator has itself); ``None`` leaves it to the simulator.
        start_method: ``"spawn"`` or ``"forkserver"`` (``"fork"`` is refused: unsafe with
            threads and GL contexts).
        step_timeout_s: a worker silent for longer during a command is killed and replaced.
        max_restarts: more sub-env crashes than this in total stop the run (an env crashing on
            every step would otherwise loop forever).
    """

    def __init__(
        self,
        factory: SubEnvFactory,
        num_envs: int,
        *,
        num_workers: int | None = None,
        seed: int = 0,
        max_episode_steps: int | None = None,
        start_method: str = "spawn",
        step_timeout_s: float | None = None,
        max_restarts: int = 100,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if num_workers is None:
            num_workers = min(num_envs, os.cpu_count() or 1)
        if not 0 <= num_workers <= num_envs:
            raise ValueError(f"num_workers must be in [0, num_envs={num_envs}], got {num_workers}")
        if start_method not in ("spawn", "forkserver"):
            raise ValueError(f"start_method must be 'spawn' or 'forkserver', got {start_method!r}")
        self.num_envs = num_envs
        self.num_workers = num_workers
        self.restart_count = 0
        self._max_restarts = max_restarts
        self._step_timeout_s = step_timeout_s
        self._obs: Obs | None = None
        self._pending_step: list[tuple[Any, list[int]]] | None = None
        self._pending_autoreset = True
        self._workers = self._start_workers(
            factory, num_workers, seed, max_episode_steps, start_method
        )
        self._finalizer = weakref.finalize(self, _close_workers, self._workers)
        self.action_space, observation_spec = self._workers[0].specs
        self.observation_spec: ObservationSpec = observation_spec
        self._episode_return = np.zeros(num_envs, dtype=np.float64)
        self._episode_length = np.zeros(num_envs, dtype=np.int64)
        self._episode_success = np.zeros(num_envs, dtype=bool)
        self._awaiting_reset = np.zeros(num_envs, dtype=bool)  # ended in a step with autoreset=False

    def _start_workers(self, factory, num_workers, seed, max_episode_steps, start_method):
        if num_workers == 0:
            return [_LocalWorker(factory, range(self.num_envs), seed, max_episode_steps)]
        context = mp.get_context(start_method)
        blocks = np.array_split(np.arange(self.num_envs), num_workers)
        workers = [
            _ProcessWorker(context, factory, [int(i) for i in block], seed, max_episode_steps)
            for block in blocks
        ]
        try:
            for worker in workers:  # start all first, so the workers build their envs in parallel
                worker.start()
            for worker in workers:
                try:
                    worker.wait_ready()
                except _WorkerLost as exc:
                    raise EnvCrashError(
                        f"env worker for sub-envs {worker.indices} died while starting ({exc}); "
                        "its traceback is on stderr. Workers are spawned: they re-import the "
                        "main script, which must guard its code with "
                        "`if __name__ == '__main__':` and cannot be read from stdin"
                    ) from exc
        except BaseException:
            _close_workers(workers)
            raise
        return workers

    # ---- Env protocol -----------------------------------------------------------------------

    def reset(
        self, seeds: int | Sequence[int] | None = None, state_ids: Sequence[int] | None = None
    ) -> Obs:
        """Start a new episode in every env and return the batched first observations.

        ``seeds``: one per env, or an int ``s`` meaning ``s, s+1, ...``; the same seed always gives
        the same first observation. ``state_ids``: one fixed initial state per env (an int: the
        same state for all); envs given the same id start identically (groups for embodied GRPO).
        Neither: the next seed of each env's own stream.
        """
        if seeds is not None and state_ids is not None:
            raise ValueError("pass seeds or state_ids, not both")
        if self._pending_step is not None:
            raise RuntimeError("reset() called between step_async() and step_wait()")
        seed_list = self._per_env("seeds", seeds)
        state_list = self._per_env("state_ids", state_ids)
        requests = [
            [(k, seed_list[i], state_list[i]) for k, i in enumerate(worker.indices)]
            for worker in self._workers
        ]
        for worker, request in zip(self._workers, requests, strict=False):
            worker.send("reset", request)
        blocks = []
        for worker, request in zip(self._workers, requests, strict=False):
            try:
                blocks.append(worker.receive(self._step_timeout_s))
            except _WorkerLost as exc:
                self._count_restart(worker.indices, f"worker process lost during reset: {exc}")
                blocks.append(self._restart_and_reset(worker, request))
        self._obs = _concat_blocks(blocks)  # workers own contiguous index blocks, in order
        self._episode_return[:] = 0.0
        self._episode_length[:] = 0
        self._episode_success[:] = False
        self._awaiting_reset[:] = False
        return copy_obs(self._obs)

    def step(self, actions: Any, env_mask: np.ndarray | None = None, autoreset: bool = True) -> StepResult:
        """Step every env (or only where ``env_mask`` is true) by one action; see
        :class:`~infinirl.envs.base.StepResult` for what ``info`` holds. ``autoreset=False``: an
        episode that ends is not restarted (its row keeps the final observation) and that env
        cannot be stepped again before :meth:`reset`."""
        self.step_async(actions, env_mask, autoreset)
        return self.step_wait()

    def step_async(self, actions: Any, env_mask: np.ndarray | None = None, autoreset: bool = True) -> None:
        """Send the actions and return at once; :meth:`step_wait` collects the result. Lets the
        caller compute something else (another stage's policy) while the simulators run."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        if self._pending_step is not None:
            raise RuntimeError("step_async() called twice without step_wait()")
        actions = self.action_space.validate(actions, self.num_envs)
        active = self._validate_mask(env_mask)
        ended = active & self._awaiting_reset
        if ended.any():
            raise RuntimeError(
                f"env(s) {np.flatnonzero(ended).tolist()} ended in a step with autoreset=False and "
                "have not been reset: call reset() first, or leave them out with env_mask"
            )
        self._pending_step = []
        self._pending_autoreset = bool(autoreset)
        for worker in self._workers:
            slots = [k for k, i in enumerate(worker.indices) if active[i]]
            indices = np.asarray(worker.indices)[slots]
            worker.send("step", slots, actions[indices], self._pending_autoreset)
            self._pending_step.append((worker, indices))

    def step_wait(self) -> StepResult:
        if self._pending_step is None:
            raise RuntimeError("step_wait() called without step_async()")
        pending, self._pending_step = self._pending_step, None
        blocks = []
        for worker, indices in pending:
            try:
                blocks.append((indices, worker.receive(self._step_timeout_s)))
            except _WorkerLost as exc:
                blocks.append(self._replace_lost_worker(worker, f"worker process lost: {exc}"))
        return self._assemble([(indices, block) for indices, block in blocks if block is not None])

    def render(self) -> np.ndarray:
        """One RGB frame per env, ``[num_envs, H, W, 3]`` uint8 (for evaluation videos)."""
        for worker in self._workers:
            worker.send("render")
        try:
            frames = [f for worker in self._workers for f in worker.receive(self._step_timeout_s)]
        except _WorkerLost as exc:
            raise EnvCrashError(f"an env worker was lost while rendering ({exc})") from exc
        return np.stack(frames)

    def offload(self) -> None:
        """CPU simulators hold no device memory: nothing to release."""

    def reload(self) -> None:
        """CPU simulators hold no device memory: nothing to restore."""

    def close(self) -> None:
        """Stop every worker and reap its process; safe to call twice."""
        self._finalizer()

    def __enter__(self) -> VectorEnv:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def worker_processes(self) -> list:
        """The live worker processes (empty in-process); for monitoring and tests."""
        return [w.process for w in self._workers if getattr(w, "process", None) is not None]

    # ---- internals --------------------------------------------------------------------------

    def _per_env(self, what: str, values: int | Sequence[int] | None) -> list[int | None]:
        if values is None:
            return [None] * self.num_envs
        if isinstance(values, int | np.integer):
            if what == "state_ids":
                return [int(values)] * self.num_envs
            return [int(values) + i for i in range(self.num_envs)]
        values = [int(v) for v in values]
        if len(values) != self.num_envs:
            raise ValueError(f"expected {self.num_envs} {what} (one per env), got {len(values)}")
        return values

    def _validate_mask(self, env_mask: np.ndarray | None) -> np.ndarray:
        if env_mask is None:
            return np.ones(self.num_envs, dtype=bool)
        mask = np.asarray(env_mask, dtype=bool)
        if mask.shape != (self.num_envs,):
            raise ValueError(f"expected env_mask of shape ({self.num_envs},), got {mask.shape}")
        return mask

    def _replace_lost_worker(self, worker, reason: str) -> tuple[np.ndarray, _BlockStep]:
        """Start a new process for a dead worker; ALL its envs lost their episodes, stepped or
        not, so all are reported truncated and restarted (counted in :meth:`_assemble`)."""
        count = len(worker.indices)
        fresh = self._restart_and_reset(worker, [(k, None, None) for k in range(count)])
        block = _BlockStep(
            obs=fresh,
            reward=np.zeros(count, dtype=np.float32),
            terminated=np.zeros(count, dtype=bool),
            truncated=np.ones(count, dtype=bool),
            success=np.zeros(count, dtype=bool),
            final_obs={},
            restart_errors=dict.fromkeys(range(count), reason),
        )
        return np.asarray(worker.indices), block

    def _restart_and_reset(self, worker, requests) -> Obs:
        """Replace a lost worker process and reset its envs; a replacement that dies too means
        the problem is not transient, so the run stops with the reason."""
        try:
            worker.restart()
            worker.send("reset", requests)
            return worker.receive(self._step_timeout_s)
        except _WorkerLost as exc:
            raise EnvCrashError(
                f"env worker for sub-envs {worker.indices} died again right after a restart ({exc})"
            ) from exc

    def _count_restart(self, indices: Sequence[int], reason: str) -> None:
        self.restart_count += len(indices)
        logger.warning("env(s) %s restarted: %s", list(indices), reason)
        if self.restart_count > self._max_restarts:
            raise EnvCrashError(
                f"{self.restart_count} sub-env restarts exceed max_restarts={self._max_restarts}; "
                f"last crash (envs {list(indices)}):\n{reason}"
            )

    def _assemble(self, blocks: list[tuple[np.ndarray, _BlockStep]]) -> StepResult:
        """The workers' blocks -> one batched :class:`StepResult`; updates the current obs."""
        n = self.num_envs
        reward = np.zeros(n, dtype=np.float32)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        success = np.zeros(n, dtype=bool)
        stepped = np.zeros(n, dtype=bool)
        restarted = np.zeros(n, dtype=bool)
        final_rows: dict[int, Obs] = {}
        restart_errors: dict[int, str] = {}
        for indices, block in blocks:
            for position, error in block.restart_errors.items():
                i = int(indices[position])
                restart_errors[i] = error
                # a crashed env has no final observation: keep its last known one
                final_rows[i] = _copy_row(self._obs, i)
            for position, row in block.final_obs.items():
                final_rows[int(indices[position])] = row
            set_obs_rows(self._obs, indices, block.obs)
            reward[indices] = block.reward
            terminated[indices] = block.terminated
            truncated[indices] = block.truncated
            success[indices] = block.success
            stepped[indices] = True
        for i, error in restart_errors.items():
            restarted[i] = True
            self._count_restart([i], error)
        done = terminated | truncated
        obs = copy_obs(self._obs)
        final_obs = obs  # rows are only valid where final_obs_mask: share when nothing ended
        if final_rows:
            final_obs = copy_obs(obs)
            for i, row in final_rows.items():
                set_obs_rows(final_obs, [i], collate_obs([row]))
        self._episode_return += reward
        self._episode_length += stepped & ~restarted
        self._episode_success |= success
        info = {
            "success": success,
            "final_obs": final_obs,
            "final_obs_mask": done,
            "episode_return": np.where(done, self._episode_return, 0.0).astype(np.float32),
            "episode_length": np.where(done, self._episode_length, 0),
            "episode_success": done & self._episode_success,
            "restarted": restarted,
            "restart_errors": restart_errors,
        }
        self._episode_return[done] = 0.0
        self._episode_length[done] = 0
        self._episode_success[done] = False
        if not self._pending_autoreset:  # a crashed env was rebuilt and reset anyway: also ended
            self._awaiting_reset |= done
        return StepResult(obs, reward, terminated, truncated, info)


def _concat_blocks(blocks: Sequence[Obs]) -> Obs:
    """Batched observations of consecutive env blocks -> one batch over all envs."""
    return {
        key: (
            [text for block in blocks for text in block[key]]
            if isinstance(first, list)
            else np.concatenate([block[key] for block in blocks])
        )
        for key, first in blocks[0].items()
    }


def _copy_row(obs: Obs, index: int) -> Obs:
    """Env ``index``'s row of a batched observation, sharing no buffer with it."""
    row = obs_row(obs, index)
    return {key: value if isinstance(value, str) else np.array(value) for key, value in row.items()}
