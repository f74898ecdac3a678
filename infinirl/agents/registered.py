"""The built-in agent environments, registered on import (plugins come through the
``infinirl.agent_envs`` entry point of :data:`AGENT_ENVS`, or by dotted path)."""

from __future__ import annotations

import importlib
from collections.abc import Callable

from infinirl.agents.loop import AGENT_ENVS, AgentEnv

__all__ = ["AGENT_ENVS", "load_agent_envs", "resolve_agent_env"]

# Imported on first use, so a run without agents never imports tools or the sandbox.
_ENV_MODULES = ("infinirl.agents.tool_env", "infinirl.agents.coding.env", "infinirl.agents.search")


def load_agent_envs():
    for module in _ENV_MODULES:
        importlib.import_module(module)
    return AGENT_ENVS


def resolve_agent_env(name: str) -> Callable[..., AgentEnv]:
    """The environment class (or factory) ``name``: a registered name, or ``package.module:Class``
    for one of the user's own, importable wherever the rollout runs."""
    if ":" not in name:
        return load_agent_envs().get(name)
    module_name, _, attribute = name.partition(":")
    try:
        target = importlib.import_module(module_name)
    except ImportError as error:
        raise ImportError(f"agent environment {name!r}: cannot import module {module_name!r} ({error}); is it "
                          "installed or on PYTHONPATH?") from error
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise AttributeError(f"agent environment {name!r}: module {module_name!r} has no {attribute!r}")
        target = getattr(target, part)
    if not callable(target):
        raise TypeError(f"agent environment {name!r} is a {type(target).__name__}, not a class or factory")
    return target
