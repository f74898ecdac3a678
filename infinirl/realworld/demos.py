"""Scripted demonstration policies for robots, the source of RLPD's demonstrations buffer.

A demo policy maps the robot's present :class:`~infinirl.realworld.driver.RobotObservation` (what a
person teleoperating would see, plus what a simulator knows) to a normalised ``[-1, 1]`` action of
:class:`~infinirl.realworld.robot_env.RobotEnv`. Policies are entries of :data:`DEMO_POLICIES`,
built as ``factory(env, seed=..., noise_std=...)``:

* ``sawyer_goal``: straight toward MetaWorld's goal (``info["state"]``'s last three entries), for
  reach tasks;
* ``metaworld_expert``: MetaWorld's scripted policy of the task (:mod:`infinirl.envs.experts`),
  whose per-simulator-step hand moves are rescaled to one control period of ``delta`` actions.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from infinirl.realworld.driver import RobotObservation
from infinirl.realworld.robot_env import RobotEnv
from infinirl.registry import Registry

__all__ = ["DEMO_POLICIES", "DemoPolicy", "make_demo_policy"]

_METAWORLD_STEP_S = 0.0125  # MetaWorld's frame_skip x timestep
_METAWORLD_ACTION_SCALE = 0.01  # metres the hand moves per unit of action per MetaWorld step


class DemoPolicy(Protocol):
    def act(self, observation: RobotObservation) -> np.ndarray: ...


DEMO_POLICIES: Registry[Callable[..., DemoPolicy]] = Registry("robot demo policy")


class _Noisy:
    def __init__(self, env: RobotEnv, seed: int, noise_std: float) -> None:
        if env.spec.action_mode != "delta":
            raise ValueError("scripted demo policies emit delta actions; set the env's action_mode to 'delta'")
        self.env, self.noise_std = env, float(noise_std)
        self.rng = np.random.default_rng([seed, 0xDE30])

    def _finish(self, action: np.ndarray) -> np.ndarray:
        if self.noise_std:
            action = action + self.rng.normal(0.0, self.noise_std, action.shape)
        return np.clip(action, -1.0, 1.0).astype(np.float32)


@DEMO_POLICIES.register("sawyer_goal")
class SawyerGoalPolicy(_Noisy):
    """Move the hand straight to the goal, gripper open."""

    def act(self, observation: RobotObservation) -> np.ndarray:
        state = np.asarray(observation.info["state"], np.float64)
        move = np.clip((state[-3:] - state[:3]) / self.env.max_step, -1.0, 1.0)
        return self._finish(np.append(move, 1.0))


@DEMO_POLICIES.register("metaworld_expert")
class MetaWorldExpertPolicy(_Noisy):
    """MetaWorld's scripted policy of ``task``, rescaled to delta actions of one control period."""

    def __init__(self, env: RobotEnv, seed: int, noise_std: float, task: str = "reach-v3") -> None:
        super().__init__(env, seed, noise_std)
        from infinirl.envs.experts import make_expert

        self.expert = make_expert("metaworld", task)
        steps_per_tick = max(1, round(env.robot_spec.control_period_s / _METAWORLD_STEP_S))
        self.move_scale = _METAWORLD_ACTION_SCALE * steps_per_tick / env.max_step

    def act(self, observation: RobotObservation) -> np.ndarray:
        state = np.asarray(observation.info["state"], np.float32)
        expert = np.asarray(self.expert.act({"state": state}), np.float64)
        gripper = -expert[3]  # MetaWorld: +1 closes; here -1 closes
        return self._finish(np.append(expert[:3] * self.move_scale, gripper))


def make_demo_policy(name: str, env: RobotEnv, *, seed: int = 0, noise_std: float = 0.0, **options) -> DemoPolicy:
    return DEMO_POLICIES.get(name)(env, seed=seed, noise_std=noise_std, **options)
