"""The tool-calling environment (``rollout.agent.env: tools``): each model turn that ends with a
tool call is parsed in the configured call format, its calls run (concurrently, each with its
tool's timeout), and the results, or what was wrong with a call, come back as the observation, one
per call in the order the calls were written, inside the observation template (the call format's
by default: ``hermes`` answers in a ChatML user turn, ``tags`` right after the call). A turn
without a call is the answer and ends the trajectory.

The calls run on an event loop of the environment's own, in a daemon thread that lives as long as
the environment; work a tool hands to a thread (``asyncio.to_thread``) runs in daemon threads too.
A tool past its timeout is abandoned at once: its thread may run on, but nothing waits for it (a
per-call ``asyncio.run`` would wait for it when closing its loop)."""

from __future__ import annotations

import asyncio
import concurrent.futures as futures
import threading
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
        self._loop: _LoopThread | None = None

    def step(self, turn: str) -> AgentStep:
        parsed = self.format.parse(turn, self.tools)
        if not parsed.calls and not parsed.errors:
            return AgentStep(done=True)
        calls = list(parsed.calls[:self.max_calls_per_turn])
        results = self._run(_run_all(self.tools, calls)) if calls else []
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

    def close(self) -> None:
        if self._loop is not None:
            self._loop.close()
            self._loop = None

    def _run(self, coroutine):
        if self._loop is None:
            self._loop = _LoopThread()
        return self._loop.run(coroutine)


async def _run_all(tools, calls):
    return await asyncio.gather(*(call_tool(tools[call.name], call.arguments) for call in calls))


class _LoopThread:
    """An event loop running in a daemon thread, whose default executor (``asyncio.to_thread``)
    starts a daemon thread per call: a call a timeout abandoned neither blocks the loop nor the
    interpreter's exit."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.loop.set_default_executor(_DaemonThreads())
        self.thread = threading.Thread(target=self._serve, name="tool-loop", daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_forever()
        finally:  # a step abandoned by the agent loop may still be awaiting: cancel it
            tasks = asyncio.all_tasks(self.loop)
            for task in tasks:
                task.cancel()
            self.loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
            self.loop.close()

    def run(self, coroutine):
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result()

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)


class _DaemonThreads(futures.ThreadPoolExecutor):
    """A daemon thread per call. (A loop's default executor must be a ThreadPoolExecutor; its own
    workers are joined at exit, so a hung call would keep the process alive.)"""

    def submit(self, fn, /, *args, **kwargs):
        future: futures.Future = futures.Future()

        def work() -> None:
            if not future.set_running_or_notify_cancel():
                return
            try:
                result = fn(*args, **kwargs)
            except BaseException as exc:  # noqa: BLE001 - handed to whoever awaits the call
                future.set_exception(exc)
            else:
                future.set_result(result)

        threading.Thread(target=work, name="tool-call", daemon=True).start()
        return future
