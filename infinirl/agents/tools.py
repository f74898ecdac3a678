"""Tools an agent calls: the interface, the registry, and the built-ins (calculator, python).

A tool declares a name, a description and JSON-schema parameters (what chat templates render for
the model), and implements ``async run(**arguments) -> str``. Callers go through :func:`call_tool`,
which checks the arguments against the schema, bounds the call by the tool's timeout, times it, and
turns every failure (bad arguments, an exception, a timeout) into a :class:`ToolResult` whose text
the model sees. It never raises into the agent loop.

Adding a tool: subclass :class:`Tool` and register the class::

    @TOOLS.register("search")
    class SearchTool(Tool):
        name = "search"
        description = "Look a query up in the local corpus."
        parameters = {"type": "object", "properties": {"query": {"type": "string"}}, "required": ["query"]}

        async def run(self, query: str) -> str:
            ...

Installed packages add tools through the ``infinirl.tools`` entry-point group.
"""

from __future__ import annotations

import abc
import asyncio
import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

from infinirl.agents.calculator import CalculatorError, evaluate, format_number
from infinirl.agents.sandbox import Sandbox, SandboxLimits, SandboxResult
from infinirl.registry import Registry

__all__ = [
    "TOOLS",
    "CalculatorTool",
    "PythonTool",
    "Tool",
    "ToolResult",
    "call_tool",
    "make_tool",
    "validate_arguments",
]

logger = logging.getLogger(__name__)

TOOLS: Registry[Callable[..., Tool]] = Registry("tool", entry_point_group="infinirl.tools")

JSON_TYPES: dict[str, tuple[type, ...]] = {
    "string": (str,),
    "integer": (int,),
    "number": (int, float),
    "boolean": (bool,),
    "object": (dict,),
    "array": (list,),
    "null": (type(None),),
}


class Tool(abc.ABC):
    """One callable tool. Subclasses set the class attributes and implement :meth:`run`."""

    name: ClassVar[str]
    description: ClassVar[str]
    parameters: ClassVar[Mapping[str, Any]]  # a JSON schema of type "object"
    timeout_s: float = 10.0  # an instance may override it

    @abc.abstractmethod
    async def run(self, **arguments: Any) -> str:
        """The observation text for the model. Raise (any exception) to report a failure."""

    def spec(self) -> dict[str, Any]:
        """The function description chat templates take (``tokenizer.apply_chat_template(tools=...)``)."""
        return {
            "type": "function",
            "function": {"name": self.name, "description": self.description, "parameters": dict(self.parameters)},
        }

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


@dataclasses.dataclass(kw_only=True, frozen=True)
class ToolResult:
    """The outcome of one tool call: ``text`` goes back to the model either way."""

    name: str
    text: str
    ok: bool
    wall_time_s: float
    error: str | None = None  # "arguments", "timeout", "exception" or "unknown_tool" when not ok


def type_matches(value: Any, expected: str) -> bool:
    if expected in ("integer", "number") and isinstance(value, bool):
        return False
    return isinstance(value, JSON_TYPES.get(expected, (object,)))


def validate_arguments(parameters: Mapping[str, Any], arguments: Any) -> list[str]:
    """What is wrong with ``arguments`` for the schema ``parameters`` (empty when nothing): an
    object, every required key present, no unknown key (unless ``additionalProperties``), and each
    declared ``type``/``enum`` respected. The messages are meant for the model."""
    if not isinstance(arguments, Mapping):
        return [f"arguments must be a JSON object, got {type(arguments).__name__}"]
    properties = parameters.get("properties", {})
    problems = [f"missing required argument {key!r}" for key in parameters.get("required", []) if key not in arguments]
    for key, value in arguments.items():
        schema = properties.get(key)
        if schema is None:
            if not parameters.get("additionalProperties", False):
                problems.append(f"unknown argument {key!r}; expected {', '.join(map(repr, properties)) or 'none'}")
            continue
        expected = schema.get("type")
        types = expected if isinstance(expected, list) else [expected] if expected else []
        if types and not any(type_matches(value, kind) for kind in types):
            problems.append(f"argument {key!r} must be of type {'/'.join(types)}, got {type(value).__name__}")
        elif "enum" in schema and value not in schema["enum"]:
            problems.append(f"argument {key!r} must be one of {schema['enum']}, got {value!r}")
    return problems


async def call_tool(tool: Tool, arguments: Any, *, timeout_s: float | None = None) -> ToolResult:
    """Run ``tool`` with ``arguments``; every failure becomes an error :class:`ToolResult`."""
    started = time.monotonic()
    timeout_s = tool.timeout_s if timeout_s is None else timeout_s

    def result(text: str, error: str | None = None) -> ToolResult:
        outcome = ToolResult(name=tool.name, text=text, ok=error is None, wall_time_s=time.monotonic() - started,
                             error=error)
        logger.debug("tool %s: %s in %.3f s", tool.name, error or "ok", outcome.wall_time_s)
        return outcome

    problems = validate_arguments(tool.parameters, arguments)
    if problems:
        return result(f"Error: bad arguments for tool {tool.name!r}: {'; '.join(problems)}", "arguments")
    try:
        text = await asyncio.wait_for(tool.run(**arguments), timeout_s)
    except asyncio.TimeoutError:
        return result(f"Error: tool {tool.name!r} timed out after {timeout_s:g} s", "timeout")
    except Exception as error:  # noqa: BLE001 - a tool's failure is an observation, never a crash
        return result(f"Error: tool {tool.name!r} failed: {type(error).__name__}: {error}", "exception")
    if not isinstance(text, str):
        return result(f"Error: tool {tool.name!r} returned {type(text).__name__}, not text", "exception")
    return result(text)


def make_tool(name: str, **options: Any) -> Tool:
    """The registered tool ``name``, built with ``options``."""
    tool = TOOLS.get(name)(**options)
    if tool.name != name:
        raise ValueError(f"tool registered as {name!r} calls itself {tool.name!r}; register it under its name")
    return tool


# ----------------------------------------------------------------------------- built-ins


@TOOLS.register("calculator")
class CalculatorTool(Tool):
    """Exact arithmetic (:mod:`infinirl.agents.calculator`)."""

    name = "calculator"
    description = ("Evaluate an arithmetic expression exactly: integers, decimals, + - * / // % ** and "
                   "parentheses, abs/min/max/round. Example: 123456 * 789 + 1/4")
    parameters = {
        "type": "object",
        "properties": {"expression": {"type": "string", "description": "the expression, e.g. 12 * (3 + 4)"}},
        "required": ["expression"],
    }

    def __init__(self, *, timeout_s: float = 5.0) -> None:
        self.timeout_s = timeout_s

    async def run(self, expression: str) -> str:
        try:
            return format_number(evaluate(expression))
        except CalculatorError as error:
            raise ValueError(str(error)) from None


def summarize_run(result: SandboxResult, max_chars: int) -> str:
    """The model's view of a sandboxed run: stdout, then stderr and how it ended when not cleanly."""
    if result.error:
        return f"Error: {result.error}"
    parts = [result.stdout.rstrip("\n")] if result.stdout else []
    if result.stdout_truncated:
        parts.append("[stdout truncated]")
    if result.stderr:
        parts.append("[stderr]\n" + result.stderr.rstrip("\n") + ("\n[stderr truncated]" if result.stderr_truncated
                                                                  else ""))
    if result.limit is not None:
        parts.append(f"[stopped: {result.limit} limit]")
    elif result.exit_code not in (0, None):
        parts.append(f"[exit code {result.exit_code}]")
    elif result.exit_code is None:
        parts.append(f"[killed by signal {result.signal}]")
    text = "\n".join(parts) or "[no output]"
    return text if len(text) <= max_chars else text[: max_chars - 20] + "\n[output truncated]"


@TOOLS.register("python")
class PythonTool(Tool):
    """Runs Python code in the :class:`~infinirl.agents.sandbox.Sandbox` and reports what it printed."""

    name = "python"
    description = ("Run a Python 3 program in a sandbox (no network, no files outside its working directory, "
                   "limited time and memory) and return what it prints. Use print() to see results.")
    parameters = {
        "type": "object",
        "properties": {"code": {"type": "string", "description": "a complete Python program"}},
        "required": ["code"],
    }

    def __init__(
        self,
        *,
        sandbox: Sandbox | None = None,
        limits: SandboxLimits | None = None,
        max_concurrent: int = 4,
        max_chars: int = 4000,
        timeout_s: float | None = None,
    ) -> None:
        self.sandbox = sandbox or Sandbox(limits, max_concurrent=max_concurrent)
        self.max_chars = max_chars
        # The sandbox's own wall-time limit ends a run; this outer bound covers waiting for a slot too.
        self.timeout_s = timeout_s if timeout_s is not None else self.sandbox.limits.wall_time_s + 30.0

    async def run(self, code: str) -> str:
        return summarize_run(await self.sandbox.run(code), self.max_chars)
