"""Vectorised environments for embodied RL: one protocol, one subprocess vectoriser, adapters.

* ``base``           the :class:`Env` / :class:`SubEnv` protocols, :class:`StepResult`, spaces;
* ``vector``         :class:`VectorEnv`, the one vectoriser (auto-reset, restarts, episode stats),
  with its worker processes in ``vector_worker`` and what they run in ``episode_slots``;
* ``chunking``       :class:`ActionChunkEnv`, K actions per step;
* ``registry``       :data:`ENVS`, :func:`make_env` (``make_env("metaworld:reach-v3", 8)``) and
  :func:`check_env_kwargs` (an option the family does not take, refused before anything is built);
* ``options``        :class:`EnvOptions`, which options a family takes, read off signatures;
* adapters           ``gymnasium_env``, ``metaworld_env``, ``maniskill_env``, ``libero_env``.

Every spawned env worker imports this package, so it imports numpy and the standard library only;
simulators are imported by the adapter a worker runs.
"""

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
from infinirl.envs.options import EnvOptions
from infinirl.envs.registry import ENVS, check_env_kwargs, env_options, make_env
from infinirl.envs.vector import SubEnvFactory, VectorEnv

__all__ = [
    "ENVS",
    "ActionChunkEnv",
    "ActionSpace",
    "ArraySpec",
    "Env",
    "EnvCrashError",
    "EnvOptions",
    "Obs",
    "ObservationSpec",
    "StepResult",
    "SubEnv",
    "SubEnvFactory",
    "SubStep",
    "VectorEnv",
    "check_env_kwargs",
    "collate_obs",
    "env_options",
    "make_env",
]

