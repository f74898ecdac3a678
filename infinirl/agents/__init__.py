"""Agentic RL: multi-turn rollouts in which the model calls tools between its turns, a sandbox for
model-written code, tools, and tool-call formats.

See docs/agents.md. Modules: :mod:`~infinirl.agents.loop` (multi-turn rollouts: ``AgentRollout``,
the ``AgentEnv`` interface, the ``AGENT_ENVS`` registry), :mod:`~infinirl.agents.tool_env` (the
tool-calling environment), :mod:`~infinirl.agents.sandbox` (isolated, limited code execution),
:mod:`~infinirl.agents.calculator` (exact arithmetic without eval), :mod:`~infinirl.agents.tools`
(the tool interface, the ``TOOLS`` registry, built-ins), :mod:`~infinirl.agents.tool_calls` (how
calls are written and parsed, the ``CALL_FORMATS`` registry).
"""

from infinirl.agents.sandbox import LimitHit, Sandbox, SandboxLimits, SandboxResult
from infinirl.agents.tool_calls import (
    CALL_FORMATS,
    CallFormat,
    ParsedTurn,
    ToolCall,
    ToolCallError,
    make_call_format,
)
from infinirl.agents.tools import TOOLS, Tool, ToolResult, call_tool, make_tool

__all__ = [
    "CALL_FORMATS",
    "TOOLS",
    "CallFormat",
    "LimitHit",
    "ParsedTurn",
    "Sandbox",
    "SandboxLimits",
    "SandboxResult",
    "Tool",
    "ToolCall",
    "ToolCallError",
    "ToolResult",
    "call_tool",
    "make_call_format",
    "make_tool",
]
