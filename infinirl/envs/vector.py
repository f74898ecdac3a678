"""The one vectoriser: ``num_envs`` sub-environments in worker processes, batched as an :class:`Env`.

Every CPU simulator (MetaWorld, gymnasium, ManiSkill on CPU, LIBERO) goes through this class; an
adapter only supplies a picklable factory ``factory(env_index) -> SubEnv``. What lives here, once:

* **Processes.** ``num_workers`` processes (``spawn`` context by default: forking a process that
  holds torch threads or a GL context is unsafe), each owning a contiguous block of sub-envs, so
  the cost of a message is paid per worker, not per env. ``num_workers=0`` steps the sub-envs in
  the calling process through the same code path (cheapest for tiny envs, and easy to debug).
  Observations travel pickled through pipes: simpler than shared memory, and state or small RGB
  observations are small next to a simulator step. The worker process and the parent's handle on
  it are :mod:`~infinirl.envs.vector_worker`; what a worker does with its sub-envs is
  :mod:`~infinirl.envs.episode_slots`.
* **Auto-reset.** An env whose episode ends is reset at once; its last observation goes to
  ``info["final_obs"]``. Each env draws its episode seeds from its own stream, so a run is
  reproducible from ``seed`` alone, and envs reset to the same ``state_id`` stay in lockstep.
  ``step(..., autoreset=False)`` skips that reset for a step whose next observation nobody will
  use (a rollout's last step, before the next iteration resets every env with its own seed): a
  simulator reset can cost as much as many steps (MetaWorld rebuilds its scene layout). Such an
  env stays ended until ``reset``.
* **Crash recovery.** A sub-env whose ``step`` raises is rebuilt from its factory inside its
  worker; a worker process that dies (segfault, ``os._exit``, OOM kill) or exceeds
  ``step_timeout_s`` is replaced. Either way the affected episodes are reported truncated with
  ``info["restarted"]`` and training goes on; only a sub-env that cannot be rebuilt, or more than
  ``max_restarts`` crashes, stops the run, with the original traceback in the error.
* **Episode statistics.** Return, length and success-at-any-step are tracked here, in the parent,
  so they survive a worker that dies; :meth:`VectorEnv.open_episodes` reads those of the episodes
  still running.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import weakref
from collections.abc import Sequence
from typing import Any

import numpy as np

from infinirl.envs.base import (
    EnvCrashError,
    Obs,
    ObservationSpec,
    StepResult,
    SubEnvFactory,
    collate_obs,
    copy_obs,
    obs_row,
    set_obs_rows,
)
from infinirl.envs.episode_slots import BlockStep
from infinirl.envs.vector_worker import LocalWorker, ProcessWorker, WorkerLost, close_workers

__all__ = ["SubEnvFactory", "VectorEnv"]

logger = logging.getLogger(__name__)


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
        # the task each env runs, where the factory says (multi-task suites): per-task metrics
        task_names = getattr(factory, "task_names", None)
        self.task_names: list[str] | None = task_names(num_envs) if callable(task_names) else None
        self.restart_count = 0
        self._max_restarts = max_restarts
        self._step_timeout_s = step_timeout_s
        self._obs: Obs | None = None
        self._pending_step: list[tuple[Any, list[int]]] | None = None
        self._pending_autoreset = True
        self._workers = self._start_workers(
            factory, num_workers, seed, max_episode_steps, start_method
        )
        self._finalizer = weakref.finalize(self, close_workers, self._workers)
        self.action_space, observation_spec = self._workers[0].specs
        self.observation_spec: ObservationSpec = observation_spec
        self._episode_return = np.zeros(num_envs, dtype=np.float64)
        self._episode_length = np.zeros(num_envs, dtype=np.int64)
        self._episode_success = np.zeros(num_envs, dtype=bool)
        self._awaiting_reset = np.zeros(num_envs, dtype=bool)  # ended in a step with autoreset=False

    def _start_workers(self, factory, num_workers, seed, max_episode_steps, start_method):
        if num_workers == 0:
            return [LocalWorker(factory, range(self.num_envs), seed, max_episode_steps)]
        context = mp.get_context(start_method)
        blocks = np.array_split(np.arange(self.num_envs), num_workers)
        workers = [
            ProcessWorker(context, factory, [int(i) for i in block], seed, max_episode_steps)
            for block in blocks
        ]
        try:
            for worker in workers:  # start all first, so the workers build their envs in parallel
                worker.start()
            for worker in workers:
                try:
                    worker.wait_ready()
                except WorkerLost as exc:
                    raise EnvCrashError(
                        f"env worker for sub-envs {worker.indices} died while starting ({exc}); "
                        "its traceback is on stderr. Workers are spawned: they re-import the "
                        "main script, which must guard its code with "
                        "`if __name__ == '__main__':` and cannot be read from stdin"
                    ) from exc
        except BaseException:
            close_workers(workers)
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
            except WorkerLost as exc:
                self._count_restart(worker.indices, f"worker process lost during reset: {exc}")
                blocks.append(self._restart_and_reset(worker, request))
        self._obs = _concat_blocks(blocks)  # workers own contiguous index blocks, in order
        self._episode_return[:] = 0.0
        self._episode_length[:] = 0
        self._episode_success[:] = False
        self._awaiting_reset[:] = False
        return copy_obs(self._obs)

    def step(
        self,
        actions: Any,
        env_mask: np.ndarray | None = None,
        autoreset: bool = True,
        observe: bool = True,
    ) -> StepResult:
        """Step every env (or only where ``env_mask`` is true) by one action; see
        :class:`~infinirl.envs.base.StepResult` for what ``info`` holds. ``autoreset=False``: an
        episode that ends is not restarted (its row keeps the final observation) and that env
        cannot be stepped again before :meth:`reset`. ``observe=False``: this step's observation
        will not be read (an inner step of an action chunk): sub-envs that can skip their camera
        frames, whose rows then repeat an earlier frame; final and reset observations stay whole."""
        self.step_async(actions, env_mask, autoreset, observe)
        return self.step_wait()

    def step_async(
        self,
        actions: Any,
        env_mask: np.ndarray | None = None,
        autoreset: bool = True,
        observe: bool = True,
    ) -> None:
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
            worker.send("step", slots, actions[indices], self._pending_autoreset, bool(observe))
            self._pending_step.append((worker, indices))

    def step_wait(self) -> StepResult:
        if self._pending_step is None:
            raise RuntimeError("step_wait() called without step_async()")
        pending, self._pending_step = self._pending_step, None
        blocks = []
        for worker, indices in pending:
            try:
                blocks.append((indices, worker.receive(self._step_timeout_s)))
            except WorkerLost as exc:
                blocks.append(self._replace_lost_worker(worker, f"worker process lost: {exc}"))
        return self._assemble([(indices, block) for indices, block in blocks if block is not None])

    def render(self) -> np.ndarray:
        """One RGB frame per env, ``[num_envs, H, W, 3]`` uint8 (for evaluation videos)."""
        for worker in self._workers:
            worker.send("render")
        try:
            frames = [f for worker in self._workers for f in worker.receive(self._step_timeout_s)]
        except WorkerLost as exc:
            raise EnvCrashError(f"an env worker was lost while rendering ({exc})") from exc
        return np.stack(frames)

    def open_episodes(self) -> dict[str, np.ndarray]:
        """The episode each env is in the middle of: ``{"return": float64 [num_envs], "length":
        int64 [num_envs]}``, the reward summed and the steps taken since it started. Zero where
        no step has been taken since the reset, and where an episode ended in a step with
        ``autoreset=False`` (none has started since). Copies: later steps do not change them."""
        return {"return": self._episode_return.copy(), "length": self._episode_length.copy()}

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

    def _replace_lost_worker(self, worker, reason: str) -> tuple[np.ndarray, BlockStep]:
        """Start a new process for a dead worker; ALL its envs lost their episodes, stepped or
        not, so all are reported truncated and restarted (counted in :meth:`_assemble`)."""
        count = len(worker.indices)
        fresh = self._restart_and_reset(worker, [(k, None, None) for k in range(count)])
        block = BlockStep(
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
        except WorkerLost as exc:
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

    def _assemble(self, blocks: list[tuple[np.ndarray, BlockStep]]) -> StepResult:
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
