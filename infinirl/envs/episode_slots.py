"""Inside a vectoriser worker: sub-envs with seeds, time limits, auto-reset and in-place restarts.

A :class:`SlotGroup` is the block of sub-envs one worker owns (in a child process, or in the
calling process with ``num_workers=0``); each sub-env sits in an :class:`EpisodeSlot` that adds
what every simulator needs around it. The worker batches its envs' steps into one
:class:`BlockStep`, so one small message crosses the pipe per worker, not one per env.
"""

from __future__ import annotations

import logging
import traceback
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from infinirl.envs.base import ActionSpace, EnvCrashError, Obs, SubEnvFactory, collate_obs, step_takes_observe

__all__ = ["BlockStep", "EpisodeSlot", "SlotGroup", "SlotStep"]

logger = logging.getLogger(__name__)

# Distinct seed-stream namespaces, so "seed 3" and "state 3" give different episode sequences.
_SEED_STREAM = 0
_STATE_STREAM = 1


@dataclass
class SlotStep:
    """One sub-env's step as a worker reports it (pickled back to the parent)."""

    obs: Obs
    reward: float
    terminated: bool
    truncated: bool
    success: bool
    final_obs: Obs | None = None  # set when the episode ended and ``obs`` is a fresh reset
    restart_error: str | None = None  # set when the sub-env crashed and was rebuilt


@dataclass
class BlockStep:
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
    def from_slots(cls, steps: Sequence[SlotStep]) -> BlockStep:
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


class EpisodeSlot:
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
        self._env_skips_observations = step_takes_observe(self.env)

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

    def step(self, action: np.ndarray, autoreset: bool = True, observe: bool = True) -> SlotStep:
        """``observe=False``: the caller will not read this step's observation, so a sub-env that
        can (its ``step`` takes ``observe``) may skip its costly parts; not on a step where the
        time limit ends the episode, whose final observation is kept."""
        ends_by_time = self._max_episode_steps is not None and self._length + 1 >= self._max_episode_steps
        try:
            if observe or ends_by_time or not self._env_skips_observations:
                sub = self.env.step(action)
            else:
                sub = self.env.step(action, observe=False)
        except Exception:  # a crashing simulator must not take the run down
            error = traceback.format_exc()
            return SlotStep(self._rebuild(error), 0.0, False, True, False, restart_error=error)
        self._length += 1
        out_of_time = self._max_episode_steps is not None and self._length >= self._max_episode_steps
        result = SlotStep(
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
            self._env_skips_observations = step_takes_observe(self.env)
        except Exception as exc:
            raise EnvCrashError(
                f"sub-env {self.index} crashed and cannot be rebuilt:\n{traceback.format_exc()}\n"
                f"original crash:\n{error}"
            ) from exc

    def close(self) -> None:
        self.env.close()


class SlotGroup:
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
            EpisodeSlot(index, factory, (base_seed, index, generation), max_episode_steps)
            for index in indices
        ]

    def specs(self) -> tuple[ActionSpace, dict]:
        env = self.slots[0].env
        return env.action_space, dict(env.observation_spec)

    def reset(self, requests: Sequence[tuple[int, int | None, int | None]]) -> Obs:
        """``requests``: (local slot, seed, state_id) per env to reset; batched first obs."""
        return collate_obs([self.slots[k].reset(seed, state_id) for k, seed, state_id in requests])

    def step(
        self, slots: Sequence[int], actions: np.ndarray, autoreset: bool = True, observe: bool = True
    ) -> BlockStep | None:
        """Step local ``slots`` with the matching rows of ``actions``."""
        if not slots:
            return None
        return BlockStep.from_slots(
            [self.slots[k].step(a, autoreset, observe) for k, a in zip(slots, actions, strict=False)]
        )

    def render(self) -> list[np.ndarray]:
        return [slot.env.render() for slot in self.slots]

    def close(self) -> None:
        for slot in self.slots:
            slot.close()

