"""Episodes as the robot records them and the replay store keeps them, and their staleness.

An episode of ``T`` steps holds ``T + 1`` observations (``state`` and each camera's
``pixels.<name>``) and ``T`` of each step field: the ``[-1, 1]`` ``action``, ``reward``,
``terminated`` (1 only for a true end: a step limit or an aborted episode still bootstraps) and
``version``, the policy version that chose the action (``RANDOM_VERSION`` for warm-up actions drawn
uniformly before any trained weights arrived). Robots with an intervention device also record
``intervened`` (1 where the human acted: ``action`` is then the human's, the executed one, and
``version`` still that of the policy in charge of the episode).

Staleness of a step is how many versions the learner had published past the one that produced it
when the episode reached the learner (:func:`staleness_of`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from infinirl.realworld.replay import EpisodeSpec

__all__ = ["RANDOM_VERSION", "EpisodeRecorder", "Staleness", "episode_spec", "staleness_of"]

RANDOM_VERSION = -1


def episode_spec(obs_dim: int, action_dim: int, cameras: dict[str, tuple[int, int]] | None = None,
                 interventions: bool = False) -> EpisodeSpec:
    """The replay fields of a robot's episodes; ``cameras``: name -> (height, width);
    ``interventions``: the robots have an intervention device (adds ``intervened``)."""
    observations = {"state": ((obs_dim,), "float32")}
    for name, (height, width) in (cameras or {}).items():
        observations[f"pixels.{name}"] = ((height, width, 3), "uint8")
    steps = {"action": ((action_dim,), "float32"), "reward": ((), "float32"), "terminated": ((), "float32"),
             "version": ((), "int64")}
    if interventions:
        steps["intervened"] = ((), "float32")
    return EpisodeSpec(observations=observations, steps=steps)


class EpisodeRecorder:
    """Collects one episode step by step; :meth:`finish` returns it as replay-store arrays."""

    def __init__(self, first_obs: dict[str, np.ndarray]) -> None:
        self.obs = {key: [np.asarray(value)] for key, value in first_obs.items()}
        self.action: list[np.ndarray] = []
        self.reward: list[float] = []
        self.terminated: list[float] = []
        self.version: list[int] = []
        self.intervened: list[float] = []
        self.success = False
        self.mark: str | None = None
        """The human's episode mark (``success`` / ``failure``), once given."""

    def __len__(self) -> int:
        return len(self.action)

    def add(self, action: np.ndarray, obs: dict[str, np.ndarray], reward: float, terminated: bool, version: int,
            success: bool = False, intervened: bool = False) -> None:
        for key, value in obs.items():
            self.obs[key].append(np.asarray(value))
        self.action.append(np.asarray(action, np.float32))
        self.reward.append(float(reward))
        self.terminated.append(float(terminated))
        self.version.append(int(version))
        self.intervened.append(float(intervened))
        self.success = self.success or success

    def relabel_last(self, *, reward: float, terminated: bool, success: bool) -> None:
        """Give the last step another reward and end (the human's mark of the state it led to)."""
        if not self.action:
            raise RuntimeError("EpisodeRecorder.relabel_last before any step")
        self.reward[-1], self.terminated[-1] = float(reward), float(terminated)
        self.success = success

    def finish(self, interventions: bool = False) -> dict[str, np.ndarray] | None:
        """The episode's fields (with ``interventions``, also ``intervened``), or None when no step was taken."""
        if not self.action:
            return None
        episode = {"state": np.stack(self.obs["state"]).astype(np.float32)}
        for key, rows in self.obs.items():
            if key != "state":
                episode[key] = np.stack(rows).astype(np.uint8)
        episode.update(action=np.stack(self.action).astype(np.float32),
                       reward=np.asarray(self.reward, np.float32),
                       terminated=np.asarray(self.terminated, np.float32),
                       version=np.asarray(self.version, np.int64))
        if interventions:
            episode["intervened"] = np.asarray(self.intervened, np.float32)
        return episode


@dataclass(frozen=True, kw_only=True)
class Staleness:
    """Of one episode's policy steps (warm-up steps excluded): how many, their lag's sum and max."""

    policy_steps: int
    lag_sum: int
    lag_max: int

    def exceeds(self, bound: int | None) -> bool:
        return bound is not None and self.policy_steps > 0 and self.lag_max > bound


def staleness_of(versions: np.ndarray, learner_version: int) -> Staleness:
    """Lag of each step (``learner_version - version``) over the steps a policy chose."""
    versions = np.asarray(versions, np.int64)
    policy = versions[versions != RANDOM_VERSION]
    if not len(policy):
        return Staleness(policy_steps=0, lag_sum=0, lag_max=0)
    lags = learner_version - policy
    return Staleness(policy_steps=int(len(policy)), lag_sum=int(lags.sum()), lag_max=int(lags.max()))
