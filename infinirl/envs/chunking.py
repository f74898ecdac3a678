"""Action chunks: a policy emits K actions at once and the env executes all K before it asks again.

VLA and flow-matching policies predict a chunk of future actions per inference (π0-style), which
divides the number of policy calls by K. RL then works on chunk-level transitions: one observation,
one chunk of actions, the summed reward of the executed steps, done if the episode ended anywhere
in the chunk.

**An env whose episode ends inside a chunk stops there**: it is not stepped again in that chunk,
and the chunk's remaining actions for it are ignored (they were planned for an episode that is
over; running them in the freshly reset episode would corrupt its first steps). The returned
observation is then the first observation of its new episode, as with single steps, and
``info["step_mask"]`` tells which of the K actions actually ran.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from infinirl.envs.base import (
    ActionSpace,
    Env,
    Obs,
    ObservationSpec,
    StepResult,
    copy_obs,
    obs_row,
    set_obs_rows,
    step_takes_observe,
)

__all__ = ["ActionChunkEnv"]

_EPISODE_KEYS = ("episode_return", "episode_length", "episode_success")


class ActionChunkEnv:
    """Wraps an :class:`Env` so ``step`` takes actions shaped ``[num_envs, chunk_size, *action]``.

    The result is a :class:`StepResult` at chunk level: ``reward`` is the sum over the executed
    steps, ``terminated``/``truncated`` are true if the episode ended at any of them, and ``info``
    has what the wrapped env reports (``success`` becomes success at any executed step) plus
    ``step_rewards`` ``[num_envs, chunk_size]`` and ``step_mask`` (which steps ran).
    """

    def __init__(self, env: Env, chunk_size: int, skip_inner_frames: bool = True) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.env = env
        self.chunk_size = chunk_size
        # nobody reads the observations between a chunk's actions: let the env skip their frames
        self._skip_inner_frames = skip_inner_frames and step_takes_observe(env)
        self.num_envs = env.num_envs
        self.action_space: ActionSpace = env.action_space.chunked(chunk_size)
        self.observation_spec: ObservationSpec = env.observation_spec
        self.task_names: list[str] | None = getattr(env, "task_names", None)

    def reset(
        self, seeds: int | Sequence[int] | None = None, state_ids: Sequence[int] | None = None
    ) -> Obs:
        return self.env.reset(seeds=seeds, state_ids=state_ids)

    def step(self, actions: Any, env_mask: np.ndarray | None = None, autoreset: bool = True) -> StepResult:
        """``autoreset=False``: envs whose episode ends in this chunk are not reset (see
        :meth:`VectorEnv.step`); the returned observation is then their final one."""
        actions = self.action_space.validate(actions, self.num_envs)
        n, k_max = self.num_envs, self.chunk_size
        active = np.ones(n, dtype=bool) if env_mask is None else np.asarray(env_mask, bool).copy()
        step_rewards = np.zeros((n, k_max), dtype=np.float32)
        step_mask = np.zeros((n, k_max), dtype=bool)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        success = np.zeros(n, dtype=bool)
        restarted = np.zeros(n, dtype=bool)
        restart_errors: dict[int, str] = {}
        ended: dict[str, Any] | None = None  # final_obs and episode stats, filled as envs end
        result: StepResult | None = None
        for k in range(k_max):
            if not active.any():
                break
            if self._skip_inner_frames and k < k_max - 1:
                result = self.env.step(actions[:, k], env_mask=active, autoreset=autoreset, observe=False)
            else:
                result = self.env.step(actions[:, k], env_mask=active, autoreset=autoreset)
            step_mask[:, k] = active
            step_rewards[:, k] = np.where(active, result.reward, 0.0)
            success |= result.info["success"] & active
            restarted |= result.info["restarted"]
            restart_errors.update(result.info["restart_errors"])
            newly_done = result.done & active
            if newly_done.any():
                terminated |= result.terminated & active
                truncated |= result.truncated & active
                ended = _merge_rows(ended, result.info, newly_done)
            active &= ~result.done
        if result is None:
            raise ValueError("env_mask selects no env: nothing to step")
        done = terminated | truncated
        if ended is None:  # no episode ended: keep the keys, all masked out
            ended = _merge_rows(None, result.info, done)
        info = {
            "success": success,
            "final_obs": ended["final_obs"],
            "final_obs_mask": done,
            **{key: ended[key] for key in _EPISODE_KEYS},
            "restarted": restarted,
            "restart_errors": restart_errors,
            "step_rewards": step_rewards,
            "step_mask": step_mask,
        }
        return StepResult(result.obs, step_rewards.sum(axis=1), terminated, truncated, info)

    def render(self) -> np.ndarray:
        return self.env.render()

    def open_episodes(self) -> dict[str, np.ndarray]:
        """The wrapped env's running episodes (lengths in env steps, not chunks)."""
        return self.env.open_episodes()

    def offload(self) -> None:
        self.env.offload()

    def reload(self) -> None:
        self.env.reload()

    def close(self) -> None:
        self.env.close()

    def __enter__(self) -> ActionChunkEnv:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _merge_rows(ended: dict[str, Any] | None, info: dict[str, Any], rows: np.ndarray) -> dict:
    """Copy ``info``'s final observation and episode statistics into ``ended`` where ``rows``."""
    if ended is None:
        ended = {"final_obs": copy_obs(info["final_obs"])}
        ended.update({key: info[key].copy() for key in _EPISODE_KEYS})
        return ended
    for i in np.flatnonzero(rows):
        row = obs_row(info["final_obs"], i)
        set_obs_rows(ended["final_obs"], [i], {key: [value] for key, value in row.items()})
    for key in _EPISODE_KEYS:
        ended[key][rows] = info[key][rows]
    return ended
