"""Tiny deterministic sub-envs for testing the vectoriser without a simulator.

Importable by spawned worker processes as ``tests.unit.envs.toy_envs`` (the conftest next to this
file puts the repository root on ``sys.path``, which spawned children inherit).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from infinirl.envs.base import ActionSpace, ArraySpec, SubStep


class CounterEnv:
    """``state = [seed, t, action sum]``; reward = the action's first entry; the episode terminates
    after ``episode_length`` steps; ``success`` from step ``success_at`` on.

    ``crash_at``: this instance's ``crash_at``-th step (counting over its whole life) crashes in the
    way ``crash_mode`` says: ``"raise"`` an exception, ``"exit"`` kills the process, ``"hang"``
    sleeps for a minute. Rebuilt instances count from zero again.
    """

    def __init__(self, episode_length=5, success_at=3, crash_at=None, crash_mode="raise"):
        self.action_space = ActionSpace.box(-np.ones(2), np.ones(2))
        self.observation_spec = {
            "state": ArraySpec((3,), "float32"),
            "instruction": ArraySpec((), "str"),
        }
        self._episode_length = episode_length
        self._success_at = success_at
        self._crash_at = crash_at
        self._crash_mode = crash_mode
        self._life_steps = 0
        self._seed = -1
        self._t = 0
        self._sum = 0.0

    def reset(self, seed=None, state_id=None):
        self._seed = state_id if state_id is not None else seed
        self._t = 0
        self._sum = 0.0
        return self._obs()

    def step(self, action):
        self._life_steps += 1
        if self._crash_at is not None and self._life_steps == self._crash_at:
            if self._crash_mode == "exit":
                os._exit(3)
            if self._crash_mode == "hang":
                time.sleep(60)
            raise RuntimeError("toy env crashed on purpose")
        self._t += 1
        self._sum += float(np.sum(action))
        terminated = self._t >= self._episode_length
        return SubStep(self._obs(), float(action[0]), terminated, False, self._t >= self._success_at)

    def render(self):
        frame = np.zeros((4, 6, 3), dtype=np.uint8)
        frame[..., 0] = self._t
        return frame

    def close(self):
        pass

    def _obs(self):
        state = np.array([self._seed, self._t, self._sum], dtype=np.float32)
        return {"state": state, "instruction": f"count {self._seed}"}


@dataclass(frozen=True)
class CounterFactory:
    """Picklable factory; only env ``crash_index`` gets the crash settings."""

    episode_length: int = 5
    success_at: int = 3
    crash_index: int | None = None
    crash_at: int | None = None
    crash_mode: str = "raise"

    def __call__(self, index):
        crashes = index == self.crash_index
        return CounterEnv(
            self.episode_length,
            self.success_at,
            crash_at=self.crash_at if crashes else None,
            crash_mode=self.crash_mode,
        )


@dataclass(frozen=True)
class BrokenFactory:
    """A factory whose sub-env cannot even be built."""

    def __call__(self, index):
        raise ValueError(f"cannot build env {index}: simulator assets missing")


class FramedCounterEnv(CounterEnv):
    """A :class:`CounterEnv` whose observation has a camera frame (``frame``, the step count it
    was rendered at) and whose ``step`` takes ``observe``: unobserved steps repeat the last frame,
    except where the episode ends. ``renders`` counts frames drawn over the env's life."""

    def __init__(self, episode_length=5, success_at=3):
        super().__init__(episode_length, success_at)
        self.observation_spec = {
            **self.observation_spec,
            "frame": ArraySpec((1,), "int64"),
            "renders": ArraySpec((1,), "int64"),
        }
        self.renders = 0
        self._frame = None

    def reset(self, seed=None, state_id=None):
        super().reset(seed, state_id)
        return self._framed_obs(fresh=True)

    def step(self, action, observe=True):
        sub = super().step(action)
        return SubStep(self._framed_obs(fresh=observe or sub.terminated or sub.truncated),
                       sub.reward, sub.terminated, sub.truncated, sub.success)

    def _framed_obs(self, fresh):
        if fresh or self._frame is None:
            self.renders += 1
            self._frame = np.array([self._t], dtype=np.int64)
        return {**self._obs(), "frame": self._frame.copy(), "renders": np.array([self.renders])}


@dataclass(frozen=True)
class FramedCounterFactory:
    episode_length: int = 5
    success_at: int = 3

    def __call__(self, index):
        return FramedCounterEnv(self.episode_length, self.success_at)
