"""Simulator families by name, :func:`make_env`, the one way runners build environments, and
:func:`check_env_kwargs`, which refuses an option a family does not take before anything is built.

``make_env("metaworld:reach-v3", 8)`` = family ``metaworld``, task ``reach-v3``, 8 envs. A family
entry is callable as ``(task, **kwargs) -> SubEnvFactory``: it checks its arguments in the calling
process (an unknown task fails here, listing the valid ones, not as a traceback from a worker)
and returns the picklable factory that :class:`~infinirl.envs.vector.VectorEnv` hands its workers.
An entry may also have ``accepted_options(task) -> EnvOptions`` (:mod:`~infinirl.envs.options`):
the options it takes for that task, which :func:`check_env_kwargs` checks against. For an entry
without it (an out-of-tree plain function) the options are read off its signature.

The built-in entries import their adapter module only when used: adapters import heavy simulators,
and worker processes import just the adapter they run. Out-of-tree simulators register through the
``infinirl.envs`` entry-point group without touching this file.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from infinirl.envs.base import Env, SubEnvFactory
from infinirl.envs.chunking import ActionChunkEnv
from infinirl.envs.options import EnvOptions, keyword_names
from infinirl.envs.vector import VectorEnv
from infinirl.registry import Registry

__all__ = ["ENVS", "AdapterFamily", "check_env_kwargs", "env_options", "make_env", "split_env_name"]

ENVS: Registry[Callable[..., SubEnvFactory]] = Registry("environment", "infinirl.envs")


@dataclass(frozen=True, kw_only=True)
class AdapterFamily:
    """A family whose adapter lives in ``module``: ``factory`` builds its :data:`SubEnvFactory`,
    ``options`` says which options a task takes. Both are looked up on first use, so registering
    a family imports nothing."""

    module: str
    factory: str
    options: str

    def __call__(self, task: str | None, **kwargs: Any) -> SubEnvFactory:
        return getattr(importlib.import_module(self.module), self.factory)(task, **kwargs)

    def accepted_options(self, task: str | None) -> EnvOptions:
        return getattr(importlib.import_module(self.module), self.options)(task)


ENVS.add("gym", AdapterFamily(module="infinirl.envs.gymnasium_env", factory="gymnasium_factory",
                              options="gymnasium_options"))
ENVS.add("metaworld", AdapterFamily(module="infinirl.envs.metaworld_env", factory="metaworld_factory",
                                    options="metaworld_options"))
ENVS.add("maniskill", AdapterFamily(module="infinirl.envs.maniskill_env", factory="maniskill_factory",
                                    options="maniskill_options"))
ENVS.add("libero", AdapterFamily(module="infinirl.envs.libero_env", factory="libero_factory",
                                 options="libero_options"))
ENVS.add("vla_noise", AdapterFamily(module="infinirl.envs.noise_steering", factory="noise_steering_factory",
                                    options="noise_steering_options"))


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
    ``max_restarts`` go to :class:`VectorEnv`; ``max_episode_steps`` also to a family that takes
    it (MetaWorld's and LIBERO's own limits, gymnasium's and ManiSkill's ``TimeLimit``); everything
    else to the simulator family (e.g. MetaWorld's ``obs_mode="state+rgb"``, ``camera=``,
    ``image_size=``), checked first by :func:`check_env_kwargs`.
    """
    family, named_task = split_env_name(name)
    if named_task and task is not None and named_task != task:
        raise ValueError(f"task given twice: {named_task!r} in the name and task={task!r}")
    task = named_task or task
    full_name = f"{family}:{task}" if task else family
    check_env_kwargs(full_name, env_kwargs, "make_env")
    if max_episode_steps is not None and "max_episode_steps" in env_options(full_name).names:
        # the simulator's own time limit (MetaWorld's 200 steps, a LIBERO suite's horizon, a registered
        # gymnasium TimeLimit) follows the configured one: left at its default it would cut a longer
        # episode short, silently
        env_kwargs = {**env_kwargs, "max_episode_steps": max_episode_steps}
    factory = ENVS.get(family)(task, **env_kwargs)
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


def split_env_name(name: str) -> tuple[str, str | None]:
    """``"metaworld:reach-v3"`` -> ``("metaworld", "reach-v3")``; ``"gym"`` -> ``("gym", None)``."""
    family, _, task = name.partition(":")
    return family, task or None


_MAKE_ENV_ARGUMENTS = frozenset(
    name for name, parameter in inspect.signature(make_env).parameters.items()
    if parameter.kind is not parameter.VAR_KEYWORD
)
"""What make_env takes itself: in env options they would clash with the runner's own arguments."""


def env_options(name: str) -> EnvOptions:
    """The options env ``name`` (``"family:task"``) takes; an unknown family or task fails,
    listing the valid ones."""
    family, task = split_env_name(name)
    entry = ENVS.get(family)
    accepted = getattr(entry, "accepted_options", None)
    if accepted is not None:
        return accepted(task)
    names, open_ended = keyword_names(entry, skip=("task",))
    return EnvOptions(names=names, passes_others=open_ended)


def check_env_kwargs(name: str, kwargs: Mapping[str, Any], where: str) -> None:
    """Refuse any option env ``name`` (``"family:task"``) does not take, or a value outside an
    option's choices, with a one-line :class:`ValueError` that names ``where`` (the config key, e.g.
    ``"eval.env_kwargs"``), the offending keys, the family and task, and the keys it takes.

    Reads factory fields and constructor signatures; builds no simulator (ManiSkill is imported,
    which registers its tasks). An unknown family or task fails as in :func:`make_env`."""
    options = env_options(name)
    family, task = split_env_name(name)
    env = f"{family} env {task!r}" if task else f"{family} env"
    refused = []
    for key in sorted(kwargs, key=str):
        if key in _MAKE_ENV_ARGUMENTS:
            refused.append(f"{key!r} (a make_env argument, set from the env config, not an env option)")
        elif key in options.reserved:
            refused.append(f"{key!r} ({options.reserved[key]})")
        elif key not in options.names and not options.passes_others:
            refused.append(repr(key))
    if refused:
        takes = ", ".join(sorted(options.names - _MAKE_ENV_ARGUMENTS)) or "no options"
        if options.passes_others:
            takes += ", and options it passes on"
        raise ValueError(f"{where}: {env} does not take {', '.join(refused)}; it takes: {takes}")
    for key, allowed in options.choices.items():
        if key in kwargs and kwargs[key] not in allowed:
            raise ValueError(f"{where}: {key}={kwargs[key]!r} is not one of {list(allowed)} for {env}")
