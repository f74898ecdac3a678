"""How a model writes tool calls, and how a tool's answer is written back: call formats.

``hermes``: the JSON format of the Hermes / Qwen chat templates::

    <tool_call>
    {"name": "calculator", "arguments": {"expression": "12 * 7"}}
    </tool_call>

answered by ``<tool_response>\\n...\\n</tool_response>``, in a user turn of the ChatML template as
Qwen2.5's chat template writes it (:attr:`CallFormat.observation_template`). Models whose chat
template defines tools (Qwen2.5, Hermes) get the tool list from
``tokenizer.apply_chat_template(tools=[t.spec() ...])``; :meth:`CallFormat.system_prompt` writes an
equivalent instruction for the others (and the runner's prompts: it puts no ``tools=`` in them).

``tags``: one tag per tool, for models without a tool template (SmolLM2's ChatML template has
none)::

    <calculator>12 * 7</calculator>

answered by ``<result>\\n...\\n</result>`` right after the call, in the model's own turn. The
body is the tool's one argument as text, or a JSON object of arguments for a tool with several.
Only the registered tools' names are calls; other tags are ordinary text.

Parsing never raises: a turn yields the well-formed calls (known tool, arguments that fit its schema)
and a :class:`ToolCallError` with a message for the model for each malformed one (JSON nested too
deeply or holding a number too long to convert included), in the order written. A call whose
closing tag is missing at the very end of the text counts as closed, because engines may drop the
stop string they stopped at (:meth:`CallFormat.stop_strings`).
"""

from __future__ import annotations

import abc
import dataclasses
import json
import re
import textwrap
from collections.abc import Mapping, Sequence
from typing import Any

from infinirl.agents.tools import Tool, validate_arguments
from infinirl.registry import Registry

__all__ = [
    "CALL_FORMATS",
    "CallFormat",
    "HermesFormat",
    "ParsedTurn",
    "TagFormat",
    "ToolCall",
    "ToolCallError",
    "make_call_format",
]

CALL_FORMATS: Registry[type[CallFormat]] = Registry("tool-call format", entry_point_group="infinirl.call_formats")
MAX_QUOTED_CHARS = 200  # how much of a malformed call an error message quotes back


@dataclasses.dataclass(kw_only=True, frozen=True)
class ToolCall:
    """A well-formed call: a known tool and arguments that fit its schema."""

    name: str
    arguments: dict[str, Any]
    text: str  # the span of the model's text it was parsed from


@dataclasses.dataclass(kw_only=True, frozen=True)
class ToolCallError:
    """A malformed call; ``message`` is what the model is told."""

    message: str
    text: str


@dataclasses.dataclass(kw_only=True, frozen=True)
class ParsedTurn:
    """The calls of one model turn, in the order written, and the malformed ones. ``items`` holds
    both in the order written (a turn's answers go back in that order: Hermes responses carry no
    call id); built without it, it is the calls followed by the errors."""

    calls: tuple[ToolCall, ...] = ()
    errors: tuple[ToolCallError, ...] = ()
    items: tuple[ToolCall | ToolCallError, ...] = ()

    def __post_init__(self) -> None:
        if not self.items:
            object.__setattr__(self, "items", (*self.calls, *self.errors))

    @property
    def has_calls(self) -> bool:
        """Whether the turn tried to call any tool (well-formed or not): the agent loop continues."""
        return bool(self.calls or self.errors)


def quote(text: str) -> str:
    text = text.strip()
    return repr(text if len(text) <= MAX_QUOTED_CHARS else text[:MAX_QUOTED_CHARS] + "...")


def json_problem(error: ValueError | RecursionError) -> str:
    """Why a JSON text could not be read, for the model. Besides syntax errors, the decoder raises
    RecursionError for deep nesting and a plain ValueError for an integer past Python's digit limit
    (``sys.get_int_max_str_digits``)."""
    if isinstance(error, json.JSONDecodeError):
        return error.msg
    if isinstance(error, RecursionError):
        return "nested too deeply"
    if "integer string conversion" in str(error):
        return "a number too long to read"
    return str(error)[:MAX_QUOTED_CHARS]


def check_call(name: Any, arguments: Any, tools: Mapping[str, Tool], text: str) -> ToolCall | ToolCallError:
    """The call if ``name`` is a known tool and ``arguments`` fit its schema; else the error."""
    if not isinstance(name, str) or not name:
        return ToolCallError(message=f"a tool call needs a \"name\" string; got {quote(text)}", text=text)
    if name not in tools:
        known = ", ".join(sorted(tools)) or "(none)"
        return ToolCallError(message=f"unknown tool {name!r}; available tools: {known}", text=text)
    problems = validate_arguments(tools[name].parameters, arguments)
    if problems:
        return ToolCallError(message=f"bad arguments for tool {name!r}: {'; '.join(problems)}", text=text)
    return ToolCall(name=name, arguments=dict(arguments), text=text)


def collect(results: Sequence[ToolCall | ToolCallError]) -> ParsedTurn:
    return ParsedTurn(calls=tuple(r for r in results if isinstance(r, ToolCall)),
                      errors=tuple(r for r in results if isinstance(r, ToolCallError)), items=tuple(results))


def guarded(parse_one, span: str, *args) -> ToolCall | ToolCallError:
    """One call's parse, whatever its text: a failure the parser did not foresee (reading or
    checking deeply nested or oversized values) makes this call malformed, not the whole turn."""
    try:
        return parse_one(span, *args)
    except (ValueError, RecursionError) as error:
        return ToolCallError(message=f"the tool call could not be read ({json_problem(error)}): {quote(span)}",
                             text=span)


class CallFormat(abc.ABC):
    """Writes and reads one tool-call convention."""

    name: str
    observation_template: str = "{results}"
    """The default text around a turn's results (``{results}``): where they go in the chat
    template, e.g. a user turn that closes the model's turn and opens its next one."""

    @abc.abstractmethod
    def parse(self, text: str, tools: Mapping[str, Tool]) -> ParsedTurn:
        """The calls in ``text`` (a model turn). Never raises."""

    @abc.abstractmethod
    def format_call(self, name: str, arguments: Mapping[str, Any], tools: Mapping[str, Tool]) -> str:
        """The text of a call, as the model is expected to write it (for prompts and tests)."""

    @abc.abstractmethod
    def format_results(self, texts: Sequence[str]) -> str:
        """The text that answers a turn's calls: one block per call's result (or error message)."""

    def result_parts(self, texts: Sequence[str]) -> tuple[tuple[str, bool], ...]:
        """:meth:`format_results` as ``(text, cuttable)`` pieces (``AgentStep.parts``): a result's
        own text may be cut to fit the budget, the tags around it are kept. A format that does not
        say gives one cuttable piece."""
        return ((self.format_results(texts), True),)

    @abc.abstractmethod
    def stop_strings(self, tools: Mapping[str, Tool]) -> tuple[str, ...]:
        """Strings the engine stops generating at, so the loop can run the call."""

    @abc.abstractmethod
    def system_prompt(self, tools: Mapping[str, Tool]) -> str:
        """An instruction listing ``tools`` and how to call them, for a system message."""


@CALL_FORMATS.register("hermes")
class HermesFormat(CallFormat):
    """``<tool_call>{"name": ..., "arguments": {...}}</tool_call>`` (Hermes, Qwen2.5, Qwen3)."""

    name = "hermes"
    OPEN, CLOSE = "<tool_call>", "</tool_call>"
    RESULT_OPEN, RESULT_CLOSE = "<tool_response>\n", "\n</tool_response>"
    # Qwen2.5's template: the model's turn ends after its calls, the responses come in one user turn.
    observation_template = "<|im_end|>\n<|im_start|>user\n{results}<|im_end|>\n<|im_start|>assistant\n"
    PATTERN = re.compile(r"<tool_call>(.*?)(?:</tool_call>|\Z)", re.DOTALL)

    def parse(self, text: str, tools: Mapping[str, Tool]) -> ParsedTurn:
        if not isinstance(text, str):
            return ParsedTurn(errors=(ToolCallError(message="the turn is not text", text=repr(text)),))
        return collect([guarded(self.parse_one, match.group(0), match.group(1), tools)
                        for match in self.PATTERN.finditer(text)])

    def parse_one(self, span: str, body: str, tools: Mapping[str, Tool]) -> ToolCall | ToolCallError:
        expected = '{"name": <tool name>, "arguments": {<argument>: <value>, ...}}'
        try:
            call = json.loads(body)
        except (ValueError, RecursionError) as error:
            return ToolCallError(message=f"invalid JSON in {self.OPEN} ({json_problem(error)}): {quote(body)}; "
                                         f"expected {expected}", text=span)
        if not isinstance(call, dict):
            return ToolCallError(message=f"a tool call must be a JSON object {expected}; got {quote(body)}",
                                 text=span)
        arguments = call.get("arguments", {})
        if isinstance(arguments, str):  # some models write the arguments as a JSON string
            try:
                arguments = json.loads(arguments)
            except (ValueError, RecursionError) as error:
                return ToolCallError(message=f"\"arguments\" is not a JSON object ({json_problem(error)}): "
                                             f"{quote(arguments)}", text=span)
        return check_call(call.get("name"), arguments, tools, span)

    def format_call(self, name: str, arguments: Mapping[str, Any], tools: Mapping[str, Tool]) -> str:
        return f"{self.OPEN}\n{json.dumps({'name': name, 'arguments': dict(arguments)})}\n{self.CLOSE}"

    def format_results(self, texts: Sequence[str]) -> str:
        return "".join(text for text, _ in self.result_parts(texts))

    def result_parts(self, texts: Sequence[str]) -> tuple[tuple[str, bool], ...]:
        return blocks(texts, self.RESULT_OPEN, self.RESULT_CLOSE)

    def stop_strings(self, tools: Mapping[str, Tool]) -> tuple[str, ...]:
        return (self.CLOSE,)

    def system_prompt(self, tools: Mapping[str, Tool]) -> str:
        # The wording of Qwen2.5's chat template, so a model trained on it sees what it knows.
        listing = "\n".join(json.dumps(tool.spec()) for tool in tools.values())
        return (
            "# Tools\n\nYou may call one or more functions to assist with the user query.\n\n"
            "You are provided with function signatures within <tools></tools> XML tags:\n"
            f"<tools>\n{listing}\n</tools>\n\n"
            "For each function call, return a json object with function name and arguments within "
            "<tool_call></tool_call> XML tags:\n"
            '<tool_call>\n{"name": <function-name>, "arguments": <args-json-object>}\n</tool_call>'
        )


def blocks(texts: Sequence[str], open_: str, close: str) -> tuple[tuple[str, bool], ...]:
    """One ``open_ text close`` block per text, a newline between blocks; only the texts cuttable."""
    parts: list[tuple[str, bool]] = []
    for index, text in enumerate(texts):
        parts += [(("\n" if index else "") + open_, False), (text, True), (close, False)]
    return tuple(parts)


def sole_parameter(tool: Tool) -> tuple[str, Mapping[str, Any]] | None:
    properties = tool.parameters.get("properties", {})
    if len(properties) == 1:
        return next(iter(properties.items()))
    return None


@CALL_FORMATS.register("tags")
class TagFormat(CallFormat):
    """``<calculator>12 * 7</calculator>``: one tag per tool, for models without a tool template."""

    name = "tags"
    RESULT_OPEN, RESULT_CLOSE = "<result>", "</result>"

    def pattern(self, tools: Mapping[str, Tool]) -> re.Pattern:
        names = "|".join(re.escape(name) for name in sorted(tools, key=len, reverse=True))
        return re.compile(rf"<({names})>(.*?)(?:</\1>|\Z)", re.DOTALL)

    def parse(self, text: str, tools: Mapping[str, Tool]) -> ParsedTurn:
        if not isinstance(text, str):
            return ParsedTurn(errors=(ToolCallError(message="the turn is not text", text=repr(text)),))
        if not tools:
            return ParsedTurn()
        return collect([guarded(self.parse_one, match.group(0), match.group(1), match.group(2), tools)
                        for match in self.pattern(tools).finditer(text)])

    def parse_one(self, span: str, name: str, body: str, tools: Mapping[str, Tool]) -> ToolCall | ToolCallError:
        body = textwrap.dedent(body).strip("\n")
        if not body.strip():
            return ToolCallError(message=f"empty <{name}> call; write the input between <{name}> and </{name}>",
                                 text=span)
        sole = sole_parameter(tools[name])
        if sole is not None:
            key, schema = sole
            if schema.get("type", "string") == "string":
                return check_call(name, {key: body}, tools, span)
            try:
                value = json.loads(body)
            except (ValueError, RecursionError) as error:
                return ToolCallError(message=f"<{name}> expects a JSON {schema.get('type')} ({json_problem(error)}): "
                                             f"{quote(body)}", text=span)
            return check_call(name, {key: value}, tools, span)
        try:
            arguments = json.loads(body)
        except (ValueError, RecursionError) as error:
            return ToolCallError(message=f"<{name}> expects a JSON object of arguments ({json_problem(error)}): "
                                         f"{quote(body)}", text=span)
        return check_call(name, arguments, tools, span)

    def format_call(self, name: str, arguments: Mapping[str, Any], tools: Mapping[str, Tool]) -> str:
        sole = sole_parameter(tools[name]) if name in tools else None
        if sole is not None and sole[0] in arguments and len(arguments) == 1:
            value = arguments[sole[0]]
            body = value if isinstance(value, str) else json.dumps(value)
        else:
            body = json.dumps(dict(arguments))
        return f"<{name}>{body}</{name}>"

    def format_results(self, texts: Sequence[str]) -> str:
        return "".join(text for text, _ in self.result_parts(texts))

    def result_parts(self, texts: Sequence[str]) -> tuple[tuple[str, bool], ...]:
        return blocks(texts, f"{self.RESULT_OPEN}\n", f"\n{self.RESULT_CLOSE}")

    def stop_strings(self, tools: Mapping[str, Tool]) -> tuple[str, ...]:
        return tuple(f"</{name}>" for name in sorted(tools))

    def system_prompt(self, tools: Mapping[str, Tool]) -> str:
        lines = ["You can use tools. To call one, write its tag around the input; the answer comes back "
                 f"between {self.RESULT_OPEN} and {self.RESULT_CLOSE}. Tools:"]
        for name, tool in tools.items():
            sole = sole_parameter(tool)
            example = f"<{name}>{sole[0]}</{name}>" if sole else f"<{name}>{{\"argument\": value}}</{name}>"
            lines.append(f"- {example}: {tool.description}")
        return "\n".join(lines)


def make_call_format(name: str) -> CallFormat:
    """The registered call format ``name``."""
    return CALL_FORMATS.get(name)()
