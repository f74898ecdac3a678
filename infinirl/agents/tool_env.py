"""The tool-calling environment (``rollout.agent.env: tools``): each model turn that ends with a
tool call is parsed in the configured call format, its calls run (concurrently, each with its
tool's timeout), and the results, or what was wrong with a call, come back as the observation, one
per call in the order the calls were written, inside the observation template (the call format's
by default: ``hermes`` answers in a ChatML user turn, ``tags`` right after the call). A turn
without a call is the answer and ends the trajectory."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping, Sequence
from typing import Any

from infinirl.agents.loop import AGENT_ENVS, AgentEnv, AgentStep, template_parts
from infinirl.agents.tool_calls import ToolCallError, make_call_format
from infinirl.agents.tools import call_tool, make_tool

__all__ = ["ToolEnv"]

RESULTS = "{results}"


@AGENT_ENVS.register("tools")
class ToolEnv(AgentEnv):
    """``tools``: registered tool names (``TOOLS``); ``tool_options``: keyword options per tool;
    ``call_format``: ``tags`` (``<calculator>1+2</calculator>``) or ``hermes`` (``<tool_call>{json}
    </tool_call>``); ``max_calls_per_turn``: calls beyond it get an error message instead of a run;
    ``observation_template``: the text around a turn's results, with ``{results}`` (None: the call
    format's, :attr:`~infinirl.agents.tool_calls.CallFormat.observation_template`)."""

    def __init__(self, tools: Sequence[str] = ("calculator",), call_format: str = "tags",
                 tool_options: Mapping[str, Mapping[str, Any]] | None = None, max_calls_per_turn: int = 4,
                 observation_template: str | None = None):
        if not tools:
            raise ValueError("tools: name at least one registered tool (e.g. [calculator])")
        if max_calls_per_turn < 1:
            raise ValueError(f"max_calls_per_turn={max_calls_per_turn}: must be >= 1")
        options = dict(tool_options or {})
        unknown = set(options) - set(tools)
        if unknown:
            raise ValueError(f"tool_options names {sorted(unknown)}, which are not in tools {list(tools)}")
        self.format = make_call_format(call_format)
        template = self.format.observation_template if observation_template is None else observation_template
        if not isinstance(template, str) or RESULTS not in template:
            raise ValueError(f"observation_template={template!r} has no {RESULTS} placeholder")
        self.template = template
        self.tools = {name: make_tool(name, **options.get(name, {})) for name in tools}
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
        return AgentStep(parts=template_parts(self.template, RESULTS, self.format.result_parts(texts)), error=failed,
                         info={"tool_calls": len(calls), "tool_s": sum(r.wall_time_s for r in results)})

    def prompt_problem(self, instructions: str) -> str | None:
        missing = [name for name in self.tools if name not in instructions]
        if not missing:
            return None
        return (f"never name the tool(s) {', '.join(missing)}, and the model cannot call a tool it was not told of; "
                f"describe them in task.system_prompt, e.g. {self.format.system_prompt(self.tools)!r}")


async def _run_all(tools, calls):
    return await asyncio.gather(*(call_tool(tools[call.name], call.arguments) for call in calls))

