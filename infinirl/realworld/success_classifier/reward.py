"""The ``classifier`` reward component: a trained success classifier judges each step.

Built once per :class:`~infinirl.realworld.robot_env.RobotEnv` (on the robot's worker, where the env
is built), it loads the classifier at ``path``, checks that the env's observation gives every key it
reads with the shape it was trained on, and then gives each step the reward 1 when the success
probability of the observation after the step is at least ``threshold`` (default: the threshold saved
with the classifier), else 0. That prediction is the step's success where the robot reports none,
and with ``terminate_on_success`` it ends the episode (HIL-SERL's reward classifier).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from infinirl.realworld.driver import RobotObservation
from infinirl.realworld.robot_env import BuiltReward, RewardTerm
from infinirl.realworld.success_classifier.model import load_classifier

__all__ = ["classifier_reward"]


def classifier_reward(env: Any, *, path: str, threshold: float | None = None,
                      terminate_on_success: bool = True) -> BuiltReward:
    """The reward of the classifier at ``path`` on ``env`` (see the module docstring)."""
    classifier = load_classifier(str(path), env.observation_shapes())
    cut = classifier.threshold if threshold is None else float(threshold)
    if not 0.0 < cut < 1.0:
        raise ValueError(f"reward_options.classifier.threshold must be in (0, 1), got {threshold}")
    keys, ends = classifier.spec.obs_keys, bool(terminate_on_success)

    def reward(observation: RobotObservation, obs: dict[str, np.ndarray]) -> RewardTerm:
        probability = float(classifier.probability({key: np.asarray(obs[key])[None] for key in keys})[0])
        success = probability >= cut
        return RewardTerm(value=float(success), success=success, terminates=success and ends)

    return reward
