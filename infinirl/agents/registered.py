"""The built-in agent environments, registered on import (plugins come through the
``infinirl.agent_envs`` entry point of :data:`AGENT_ENVS`)."""

from __future__ import annotations

import importlib

from infinirl.agents.loop import AGENT_ENVS

__all__ = ["AGENT_ENVS", "load_agent_envs"]

# Imported on first use, so a run without agents never imports tools or the sandbox.
_ENV_MODULES = ("infinirl.agents.tool_env",)


def load_agent_envs():
    for module in _ENV_MODULES:
        importlib.import_module(module)
    return AGENT_ENVS
