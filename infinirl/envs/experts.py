"""Scripted expert policies by simulator family: the teachers behind demonstration datasets.

``make_expert("metaworld", "push-v3", noise_std=0.1, seed=0)`` gives an :class:`Expert` whose
``act(obs)`` maps one (unbatched) observation of our adapter to one action. A family is an entry
of :data:`EXPERTS`, callable as ``(task, *, noise_std, seed) -> Expert``; out-of-tree families
register through the ``infinirl.experts`` entry-point group.

MetaWorld ships a hand-written policy per v3 task (``metaworld.policies``); it reads the raw 39-d
observation with the goal in its last three entries, which is exactly what
:mod:`~infinirl.envs.metaworld_env` returns as ``obs["state"]`` (goal observable, MT1 convention).

Action noise (``noise_std``, Gaussian, in action units) spreads the demonstrations over states the
noiseless expert never visits, so a cloned policy sees how to recover from small errors. The action
returned is the one executed: the noisy expert action clipped to the action space, so a dataset
records what was applied, and no value outside the space the simulator would clip away.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from infinirl.envs.base import Obs
from infinirl.registry import Registry

__all__ = ["EXPERTS", "Expert", "MetaWorldExpert", "make_expert", "metaworld_expert_tasks"]


class Expert(Protocol):
    """A scripted policy for one task: ``act`` maps one observation (no env dimension) to one
    action, a float32 array inside the env's action space."""

    task: str

    def act(self, obs: Obs) -> np.ndarray: ...


EXPERTS: Registry[Callable[..., Expert]] = Registry("scripted expert family", "infinirl.experts")


def make_expert(family: str, task: str, *, noise_std: float = 0.0, seed: int | None = None) -> Expert:
    """The scripted expert of ``family`` for ``task``; an unknown family or task fails listing the
    valid ones."""
    if noise_std < 0:
        raise ValueError(f"noise_std must be >= 0, got {noise_std}")
    return EXPERTS.get(family)(task, noise_std=noise_std, seed=seed)


def metaworld_expert_tasks() -> dict[str, Any]:
    """``{task name: policy class}`` for every MetaWorld v3 task that has a scripted policy."""
    from metaworld.policies import ENV_POLICY_MAP

    return dict(ENV_POLICY_MAP)


class MetaWorldExpert:
    """MetaWorld's scripted policy for one v3 task, acting on our adapter's ``obs["state"]``."""

    ACTION_LOW = -1.0
    ACTION_HIGH = 1.0
    """MetaWorld's action space (xyz hand displacement and gripper effort); the simulator clips to it."""

    def __init__(self, task: str, *, noise_std: float = 0.0, seed: int | None = None) -> None:
        policies = metaworld_expert_tasks()
        if task not in policies:
            raise ValueError(f"no scripted MetaWorld expert for task {task!r}; tasks: {', '.join(sorted(policies))}")
        self.task = task
        self.noise_std = float(noise_std)
        self._policy = policies[task]()
        self._rng = np.random.default_rng(seed)

    def act(self, obs: Obs) -> np.ndarray:
        state = np.asarray(obs["state"], dtype=np.float64)
        if state.shape != (39,):
            raise ValueError(f"MetaWorld expert for {self.task!r} needs obs['state'] of shape (39,) (one env, "
                             f"goal observable), got {state.shape}")
        with warnings.catch_warnings():
            # The policies' proportional controllers ask for more than the action range on purpose
            # and warn about it on every such step; the clip below is the simulator's own.
            warnings.filterwarnings("ignore", message="Constant\\(s\\) may be too high")
            action = np.asarray(self._policy.get_action(state), dtype=np.float64)
        if self.noise_std > 0:
            action = action + self._rng.normal(0.0, self.noise_std, size=action.shape)
        return np.clip(action, self.ACTION_LOW, self.ACTION_HIGH).astype(np.float32)


EXPERTS.add("metaworld", MetaWorldExpert)
