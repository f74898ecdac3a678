"""A simulated human: a scripted expert that watches the policy and takes over when it drifts.

It stands in for a person in tests and demos, through the same device interface. Each step it
computes the expert's action for the present state and compares it with what the policy proposes:

* **take over**: when the distance (L2 over the robot's action entries) has exceeded
  ``threshold`` for more than ``reaction_steps`` consecutive steps (a person notices a drift only
  after a while: the policy keeps acting through the reaction delay; ``reaction_jitter`` adds a
  seeded random 0..jitter steps to each delay), it takes control;
* **correct**: it then acts with the expert for ``correct_steps`` steps and hands back;
* **marks**: with ``mark_success``, it marks ``success`` once per episode as soon as the env's own
  success signal is on; with ``give_up_steps``, it marks ``failure`` when an episode has run that
  many steps without success;
* **evaluation and demonstrations**: while the control loop holds it off
  (:meth:`~InterventionDevice.hold_off`) it neither takes over nor marks, as a person who knows those
  episodes are not theirs (its per-episode state and seeded draws stay as they were).

The expert is a scripted demo policy of :data:`~infinirl.realworld.demos.DEMO_POLICIES` (``expert``,
``expert_options``, ``noise_std``: seeded action noise), built on the env when the robot worker
calls :meth:`bind`; or any callable ``expert(observation) -> action``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from infinirl.realworld.intervention.device import INTERVENTION_DEVICES, HumanInput, InterventionDevice

__all__ = ["SimulatedHuman", "action_distance"]


def action_distance(policy_action: np.ndarray, expert_action: np.ndarray) -> float:
    """L2 distance over the expert's entries (a padded policy action's extra entries are ignored)."""
    expert = np.asarray(expert_action, np.float64).reshape(-1)
    policy = np.asarray(policy_action, np.float64).reshape(-1)[:len(expert)]
    return float(np.linalg.norm(policy - expert))


@INTERVENTION_DEVICES.register("simulated_human")
class SimulatedHuman(InterventionDevice):
    """See the module docstring."""

    def __init__(self, *, action_dim: int, expert: str | Callable[[Any], np.ndarray] = "sawyer_goal",
                 expert_options: Mapping[str, Any] | None = None, threshold: float = 0.5, reaction_steps: int = 2,
                 reaction_jitter: int = 0, correct_steps: int = 8, noise_std: float = 0.0, mark_success: bool = True,
                 give_up_steps: int | None = None, seed: int = 0) -> None:
        super().__init__(action_dim=action_dim)
        if threshold < 0 or reaction_steps < 0 or reaction_jitter < 0 or correct_steps < 1:
            raise ValueError("simulated_human: threshold, reaction_steps, reaction_jitter must be >= 0 and "
                             f"correct_steps >= 1; got {threshold}, {reaction_steps}, {reaction_jitter}, "
                             f"{correct_steps}")
        self.expert_name = expert if isinstance(expert, str) else None
        self.expert_options = dict(expert_options or {})
        self._expert: Callable[[Mapping[str, np.ndarray] | None], np.ndarray] | None = (
            None if isinstance(expert, str) else expert)
        self._success: Callable[[], bool] | None = None
        self.threshold, self.reaction_steps = float(threshold), int(reaction_steps)
        self.reaction_jitter = int(reaction_jitter)
        self.correct_steps, self.noise_std, self.seed = int(correct_steps), float(noise_std), int(seed)
        self.mark_success, self.give_up_steps = bool(mark_success), give_up_steps
        self.rng = np.random.default_rng([self.seed, 0x4E])
        self.takeovers = 0
        self.reset()

    def bind(self, env: Any) -> None:
        """Build the expert on ``env`` (a :class:`~infinirl.realworld.robot_env.RobotEnv`) and read
        success from its latest observation."""
        if self.expert_name is not None:
            from infinirl.realworld.demos import make_demo_policy

            policy = make_demo_policy(self.expert_name, env, seed=self.seed, noise_std=self.noise_std,
                                      **self.expert_options)
            self._expert = lambda observation: policy.act(env.last_observation)
        self._success = lambda: bool(env.last_observation is not None and env.last_observation.info.get("success"))

    def reset(self) -> None:
        self.drifting = 0
        self.remaining = 0
        self.steps = 0
        self.marked = False
        self.delay = self._draw_delay()

    def _draw_delay(self) -> int:
        jitter = int(self.rng.integers(0, self.reaction_jitter + 1)) if self.reaction_jitter else 0
        return self.reaction_steps + jitter

    def expert_action(self, observation: Mapping[str, np.ndarray] | None) -> np.ndarray:
        if self._expert is None:
            raise RuntimeError(f"simulated_human: expert {self.expert_name!r} is built on the robot's env; call "
                               "bind(env) first (the robot worker does)")
        expert = np.asarray(self._expert(observation), np.float32).reshape(-1)
        if len(expert) > self.action_dim:
            raise ValueError(f"simulated_human: the expert gives {len(expert)} entries, the robot takes "
                             f"{self.action_dim}")
        action = np.zeros(self.action_dim, np.float32)
        action[:len(expert)] = expert
        return action

    def _marks(self) -> tuple[str, ...]:
        if self.marked or self._success is None:
            return ()
        if self.mark_success and self._success():
            self.marked = True
            return ("success",)
        if self.give_up_steps is not None and self.steps >= self.give_up_steps:
            self.marked = True
            return ("failure",)
        return ()

    def poll(self, *, observation=None, policy_action=None) -> HumanInput:
        if self.held_off is not None:
            return HumanInput(active=False)
        marks = self._marks()
        self.steps += 1
        expert = self.expert_action(observation)
        if self.remaining > 0:
            self.remaining -= 1
            return HumanInput(active=True, action=expert, marks=marks)
        drifts = policy_action is not None and action_distance(policy_action, expert) > self.threshold
        self.drifting = self.drifting + 1 if drifts else 0
        if self.drifting > self.delay:  # the drift outlasted the reaction delay: take over
            self.drifting, self.remaining, self.delay = 0, self.correct_steps - 1, self._draw_delay()
            self.takeovers += 1
            return HumanInput(active=True, action=expert, marks=marks)
        return HumanInput(active=False, marks=marks)
