"""The tool-calling environment (``rollout.agent.env: tools``): each model turn that ends with a
tool call is parsed in the configured call format, its calls run (concurrently, each with its
tool's timeout), and the results, or what was wrong with a call, come back as the observation, one
per call in the order the calls were written. A turn without a call is the answer and ends the
trajectory."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping, Sequence
from typing import Any

from infinirl.agents.loop import AGENT_ENVS, AgentEnv, AgentStep
from infinirl.agents.tool_calls import ToolCallError, make_call_format
from infinirl.agents.tools import call_tool, make_tool

__all__ = ["ToolEnv"]


@AGENT_ENVS.register("tools")
class ToolEnv(AgentEnv):
    """``tools``: registered tool names (``TOOLS``); ``tool_options``: keyword options per tool;
    ``call_format``: ``tags`` (``<calculator>1+2</calculator>``) or ``hermes`` (``<tool_call>{json}
    </tool_call>``); ``max_calls_per_turn``: calls beyond it get an error message instead of a run."""

    def __init__(self, tools: Sequence[str] = ("calculator",), call_format: str = "tags",
                 tool_options: Mapping[str, Mapping[str, Any]] | None = None, max_calls_per_turn: int = 4):
        if not tools:
            raise ValueError("tools: name at least one registered tool (e.g. [calculator])")
        if max_calls_per_turn < 1:
            raise ValueError(f"max_calls_per_turn={max_calls_per_turn}: must be >= 1")
        options = dict(tool_options or {})
        unknown = set(options) - set(tools)
        if unknown:
            raise ValueError(f"tool_options names {sorted(unknown)}, which are not in tools {list(tools)}")
        self.tools = {name: make_tool(name, **options.get(name, {})) for name in tools}
        self.format = make_call_format(call_format)
        self.stop_strings = self.format.stop_strings(self.tools)
        self.max_calls_per_turn = max_calls_per_turn

    def step(self, turn: str) -> AgentStep:
        parsed = self.format.parse(turn, self.tools)
        if not parsed.calls and not parsed.errors:
            return AgentStep(done=True)
        calls = list(parsed.calls[:self.max_calls_per_turn])
        results = asyncio.run(_run_all(self.tools, calls)) if calls else []
        # One answer per call, in the order the calls were written: Hermes responses carry no call
        # id, so the model can only match them by position.
        answers = iter(results)
        texts, well_formed = [], 0
        for item in parsed.items:
            if isinstance(item, ToolCallError):
                texts.append(item.message)
            elif well_formed < self.max_calls_per_turn:
                well_formed += 1
                texts.append(next(answers).text)
            else:
                texts.append(f"Error: at most {self.max_calls_per_turn} tool calls per turn; {item.name!r} was not run")
        failed = bool(parsed.errors) or len(parsed.calls) > len(calls) or any(not r.ok for r in results)
        return AgentStep(observation=self.format.format_results(texts), error=failed,
                         info={"tool_calls": len(calls), "tool_s": sum(r.wall_time_s for r in results)})


async def _run_all(tools, calls):
    return await asyncio.gather(*(call_tool(tools[call.name], call.arguments) for call in calls))
