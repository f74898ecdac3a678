"""The robot worker: one rank of the ``robot`` component, a Ray worker around a
:class:`~infinirl.realworld.control_loop.RobotControlLoop`.

:class:`RobotActorWorker` builds its loop where it runs (with ``make_robot(kind, **options)``: the
kind and options of the robot its placement gave it when the cluster discovered one, else the
config's) and acts in one of two ways:

* **asynchronous** (:meth:`start`): the loop's control thread runs episodes back to back; before
  each step it loads the newest weights the learner has staged on this rank (a sync with
  ``interrupt=True`` lands beside the running loop, never in its way); each finished episode is
  put on the learner's channel by the loop's sender thread;
* **synchronous** (:meth:`collect`): the call runs whole episodes and returns them (collect, then
  update: the baseline the asynchronous pipeline is measured against).

The acting itself (warm-up, versions, safety stops, interventions) is the loop's
(:mod:`infinirl.realworld.control_loop`); the edge node runs the same loop with the edge link as
its transport (:mod:`infinirl.edge.robot_node`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from infinirl.realworld.control_loop import (
    VERSION_TENSOR,
    PolicyLayout,
    RobotControlLoop,
    RobotSetup,
    policy_layouts,
    resolve_robot,
    unit_box,
)
from infinirl.realworld.intervention.spec import InterventionSpec
from infinirl.realworld.robot_env import RobotEnvSpec
from infinirl.runtime import WeightSink, Worker
from infinirl.utils.threads import limit_threads

__all__ = ["VERSION_TENSOR", "PolicyLayout", "RobotActorWorker", "RobotSetup", "policy_layouts", "resolve_robot",
           "unit_box"]

_SEND_TIMEOUT_S = 60.0


class RobotActorWorker(Worker, WeightSink):
    """One robot + its policy copy (see the module docstring)."""

    def __init__(self, setup: RobotSetup | Sequence[RobotSetup], env: RobotEnvSpec | Sequence[RobotEnvSpec], net,
                 seed: int, num_threads: int = 1, intervention: InterventionSpec | None = None):
        limit_threads(num_threads)
        if not isinstance(setup, RobotSetup):  # a fleet: one entry per rank
            setup, env = setup[self.rank], env[self.rank]
        self.loop = RobotControlLoop(setup, env, net, seed=seed, rank=self.rank, placed=self.ctx.robot,
                                     intervention=intervention)

    @property
    def policy_version(self) -> int:
        return self.loop.policy_version

    def describe(self) -> dict:
        return self.loop.describe()

    def configure(self, layout: PolicyLayout) -> None:
        self.loop.configure(layout)

    def load_weights(self, named_tensors, version: int) -> None:
        self.loop.load_weights(named_tensors, version)

    def start(self, channel, key: str = "episodes") -> None:
        """Run episodes back to back on the loop's control thread; each finished one is put on ``channel``."""
        self.loop.start(lambda episode: channel.put(episode, key=key, timeout=_SEND_TIMEOUT_S),
                        between_steps=self.apply_staged_weights)

    def stop(self) -> dict:
        return self.loop.stop()

    def collect(self, num_episodes: int, deterministic: bool = False) -> list[dict]:
        return self.loop.collect(num_episodes, deterministic)

    def demonstrations(self, num_episodes: int, policy: str, seed: int = 0, noise_std: float = 0.0,
                       options: Mapping[str, Any] | None = None) -> list[dict]:
        return self.loop.demonstrations(num_episodes, policy, seed, noise_std, options)

    def evaluate(self, num_episodes: int) -> dict:
        return self.loop.evaluate(num_episodes)

    def record_video(self, num_episodes: int, path: str, fps: int | None = None) -> dict:
        return self.loop.record_video(num_episodes, path, fps)

    def stats(self) -> dict:
        return self.loop.stats()

    def close(self) -> None:
        self.loop.close()
