"""Acting at the edge: the policy runs next to the robot on the newest weights the link brought,
and holds the robot when it has none that may be trusted.

:class:`EdgeActor` wraps an actor network (a :class:`~infinirl.models.sac_nets.SquashedGaussianActor`
or anything with its ``sample(state, generator, deterministic)``). Before each step it loads the
newest :class:`~infinirl.edge.codec.HeldWeights` the :class:`~infinirl.edge.edge_client.EdgeClient`
received. It acts with them while the link is up or has been down for at most ``max_offline_s``;
beyond that, or before any weights arrived when ``warmup="hold"``, it returns :func:`hold_action`
(the arm keeps its target, the gripper its last command). ``warmup="random"`` acts uniformly at
random until the first weights arrive, like the robot worker's warm-up (version
:data:`~infinirl.realworld.episodes.RANDOM_VERSION`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from infinirl.edge.codec import HeldWeights
from infinirl.realworld.episodes import RANDOM_VERSION, EpisodeRecorder

__all__ = ["HOLD_VERSION", "EdgeActor", "hold_action", "load_weights", "run_episode"]

#: the version stamped on steps where the robot held instead of acting
HOLD_VERSION = -2


def hold_action(env) -> np.ndarray:
    """The action that keeps a :class:`~infinirl.realworld.robot_env.RobotEnv`'s robot where it is
    (:meth:`~infinirl.realworld.robot_env.RobotEnv.hold_action`): zero motion for the delta entries,
    the present target for the absolute ones (the gripper; every entry in absolute mode). Not the
    previous action: after a reset that is all zeros, which commands a half-open gripper and, in
    absolute mode, the middle of the arm's range."""
    return np.asarray(env.hold_action(), np.float32)


def load_weights(actor: torch.nn.Module, tensors: Mapping[str, np.ndarray]) -> None:
    """Copy ``tensors`` into ``actor``'s state (every name must exist there)."""
    own = actor.state_dict()
    unknown = sorted(set(tensors) - set(own))
    if unknown:
        raise KeyError(f"weights {unknown} from the cloud have no place in the edge's actor")
    with torch.no_grad():
        for name, array in tensors.items():
            own[name].copy_(torch.from_numpy(np.asarray(array)))


class EdgeActor:
    """See the module docstring; ``client`` may be None (acting offline from ``initial`` weights)."""

    def __init__(self, actor: torch.nn.Module, client=None, *, max_offline_s: float = 30.0,
                 warmup: str = "random", seed: int = 0) -> None:
        if warmup not in ("random", "hold"):
            raise ValueError(f"edge actor warmup {warmup!r}: choose 'random' or 'hold'")
        self.actor, self.client = actor.eval(), client
        self.max_offline_s, self.warmup = max_offline_s, warmup
        self.version: int | None = None
        self.rng = np.random.default_rng(seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.holds = 0

    def refresh(self) -> None:
        """Load the client's newest weights if they are newer than the actor's."""
        held: HeldWeights | None = self.client.weights if self.client is not None else None
        if held is not None and held.version != self.version:
            load_weights(self.actor, held.tensors)
            self.version = held.version

    @torch.no_grad()
    def act(self, env, obs: Mapping[str, np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, int]:
        """``(action, version)`` for ``obs`` (``version``: the weights used, or the warm-up / hold mark)."""
        self.refresh()
        if self.version is None:
            if self.warmup == "random":
                return self.rng.uniform(-1.0, 1.0, env.action_dim).astype(np.float32), RANDOM_VERSION
            self.holds += 1
            return hold_action(env), HOLD_VERSION
        if self.client is not None and not self.client.policy_usable(self.max_offline_s):
            self.holds += 1
            return hold_action(env), HOLD_VERSION
        state = torch.from_numpy(np.asarray(obs["state"], np.float32)[None])
        action, _, _ = self.actor.sample(state, self.generator, deterministic=deterministic)
        return action[0].numpy(), self.version


def run_episode(env, actor: EdgeActor) -> tuple[dict[str, np.ndarray] | None, dict]:
    """One episode on ``env`` with ``actor``; the episode's arrays and ``{steps, success, late_steps,
    holds}``."""
    obs = env.reset()
    recorder = EpisodeRecorder(obs)
    late = holds = 0
    while True:
        action, version = actor.act(env, obs)
        holds += int(version == HOLD_VERSION)
        step = env.step(action)
        obs = step.obs
        recorder.add(action, obs, step.reward, step.terminated, version, step.success)
        late += int(step.late)
        if step.terminated or step.truncated:
            break
    return recorder.finish(), {"steps": len(recorder), "success": recorder.success, "late_steps": late,
                               "holds": holds}
