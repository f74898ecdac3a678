"""Vectorised environments for embodied RL: one protocol, one subprocess vectoriser, adapters.

* ``base``      the :class:`Env` / :class:`SubEnv` protocols, :class:`StepResult`, spaces;
* ``vector``    :class:`VectorEnv`, the one vectoriser (worker processes, auto-reset, restarts);
* ``chunking``  :class:`ActionChunkEnv`, K actions per step;
* ``registry``  :data:`ENVS` and :func:`make_env` (``make_env("metaworld:reach-v3", 8)``);
* adapters      ``gymnasium_env``, ``metaworld_env``, ``maniskill_env``, ``libero_env``.

``make_env`` and ``ENVS`` are loaded on first use: the registry lives under
``infinirl.algorithms``, which imports torch, and every spawned env worker imports this package;
keeping it light saves each worker seconds of start-up and hundreds of MB.
"""

from typing import Any

from infinirl.envs.base import (
    ActionSpace,
    ArraySpec,
    Env,
    EnvCrashError,
    Obs,
    ObservationSpec,
    StepResult,
    SubEnv,
    SubStep,
    collate_obs,
)
from infinirl.envs.chunking import ActionChunkEnv
from infinirl.envs.vector import SubEnvFactory, VectorEnv

__all__ = [
    "ENVS",
    "ActionChunkEnv",
    "ActionSpace",
    "ArraySpec",
    "Env",
    "EnvCrashError",
    "Obs",
    "ObservationSpec",
    "StepResult",
    "SubEnv",
    "SubEnvFactory",
    "SubStep",
    "VectorEnv",
    "collate_obs",
    "make_env",
]

_LAZY = {"ENVS", "make_env"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from infinirl.envs import registry

        return getattr(registry, name)
    raise AttributeError(f"module 'infinirl.envs' has no attribute {name!r}")
