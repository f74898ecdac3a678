"""Simulator families by name, and :func:`make_env`, the one way runners build environments.

``make_env("metaworld:reach-v3", 8)`` = family ``metaworld``, task ``reach-v3``, 8 envs. A family
entry is a function ``(task, **kwargs) -> SubEnvFactory`` that checks its arguments in the calling
process (an unknown task fails here, listing the valid ones, not as a traceback from a worker)
and returns the picklable factory that :class:`~infinirl.envs.vector.VectorEnv` hands its workers.

The entries import their adapter module only when used: adapters import heavy simulators, and
worker processes import just the adapter they run. Out-of-tree simulators register through the
``infinirl.envs`` entry-point group without touching this file.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from infinirl.envs.base import Env
from infinirl.envs.chunking import ActionChunkEnv
from infinirl.envs.vector import SubEnvFactory, VectorEnv
from infinirl.registry import Registry

__all__ = ["ENVS", "make_env"]

ENVS: Registry[Callable[..., SubEnvFactory]] = Registry("environment", "infinirl.envs")


@ENVS.register("gym")
def _gymnasium(task: str | None, **kwargs: Any) -> SubEnvFactory:
    from infinirl.envs.gymnasium_env import gymnasium_factory

    return gymnasium_factory(task, **kwargs)


@ENVS.register("metaworld")
def _metaworld(task: str | None, **kwargs: Any) -> SubEnvFactory:
    from infinirl.envs.metaworld_env import metaworld_factory

    return metaworld_factory(task, **kwargs)


@ENVS.register("maniskill")
def _maniskill(task: str | None, **kwargs: Any) -> SubEnvFactory:
    from infinirl.envs.maniskill_env import maniskill_factory

    return maniskill_factory(task, **kwargs)


@ENVS.register("libero")
def _libero(task: str | None, **kwargs: Any) -> SubEnvFactory:
    from infinirl.envs.libero_env import libero_factory

    return libero_factory(task, **kwargs)


def make_env(
    name: str,
    num_envs: int,
    *,
    seed: int = 0,
    num_workers: int | None = None,
    max_episode_steps: int | None = None,
    chunk_size: int | None = None,
    start_method: str = "spawn",
    step_timeout_s: float | None = None,
    max_restarts: int = 100,
    task: str | None = None,
    **env_kwargs: Any,
) -> Env:
    """Build ``num_envs`` environments of ``name`` (``"family:task"`` or ``"family"`` with
    ``task=``) as one vectorised :class:`Env`.

    ``chunk_size=K`` wraps it in :class:`ActionChunkEnv` (actions ``[num_envs, K, *action]``).
    ``seed``, ``num_workers``, ``max_episode_steps``, ``start_method``, ``step_timeout_s`` and
    ``max_restarts`` go to :class:`VectorEnv`; everything else to the simulator family (e.g.
    MetaWorld's ``obs_mode="state+rgb"``, ``camera=``, ``image_size=``).
    """
    family, _, named_task = name.partition(":")
    if named_task and task is not None and named_task != task:
        raise ValueError(f"task given twice: {named_task!r} in the name and task={task!r}")
    build_factory = ENVS.get(family)
    factory = build_factory(named_task or task, **env_kwargs)
    env: Env = VectorEnv(
        factory,
        num_envs,
        num_workers=num_workers,
        seed=seed,
        max_episode_steps=max_episode_steps,
        start_method=start_method,
        step_timeout_s=step_timeout_s,
        max_restarts=max_restarts,
    )
    return ActionChunkEnv(env, chunk_size) if chunk_size else env
