"""Tools: the registry, argument checks, and every failure turned into an observation."""

import asyncio

import pytest

from infinirl.agents.sandbox import SandboxLimits
from infinirl.agents.tools import TOOLS, CalculatorTool, PythonTool, Tool, call_tool, make_tool, validate_arguments
from infinirl.registry import UnknownNameError


class Raising(Tool):
    name = "raising"
    description = "always fails"
    parameters = {"type": "object", "properties": {}}

    async def run(self) -> str:
        raise RuntimeError("boom")


class Hanging(Tool):
    name = "hanging"
    description = "never answers"
    parameters = {"type": "object", "properties": {}}
    timeout_s = 0.2

    async def run(self) -> str:
        await asyncio.Event().wait()
        return "unreachable"


class NotText(Tool):
    name = "not_text"
    description = "returns a number"
    parameters = {"type": "object", "properties": {}}

    async def run(self) -> str:
        return 3  # type: ignore[return-value]


SCHEMA = {
    "type": "object",
    "properties": {"q": {"type": "string"}, "k": {"type": "integer"}, "mode": {"type": "string", "enum": ["a", "b"]},
                   "x": {"type": ["number", "null"]}},
    "required": ["q"],
}


def call(tool, arguments, **kwargs):
    return asyncio.run(call_tool(tool, arguments, **kwargs))


def test_registry_holds_the_built_ins():
    assert {"calculator", "python"} <= set(TOOLS.names())
    assert isinstance(make_tool("calculator"), CalculatorTool)
    with pytest.raises(UnknownNameError, match="did you mean 'calculator'"):
        make_tool("calculater")


def test_spec_is_a_chat_template_function():
    spec = make_tool("calculator").spec()
    assert spec["type"] == "function"
    assert spec["function"]["name"] == "calculator"
    assert spec["function"]["parameters"]["required"] == ["expression"]


@pytest.mark.parametrize("arguments, problem", [
    ({"q": "x"}, None),
    ({"q": "x", "k": 3, "mode": "b", "x": None}, None),
    ({"q": "x", "x": 1.5}, None),
    ({}, "missing required argument 'q'"),
    ({"q": 1}, "'q' must be of type string"),
    ({"q": "x", "k": True}, "'k' must be of type integer"),
    ({"q": "x", "k": 1.5}, "'k' must be of type integer"),
    ({"q": "x", "mode": "c"}, "must be one of"),
    ({"q": "x", "extra": 1}, "unknown argument 'extra'"),
    ([1, 2], "must be a JSON object"),
    ("q", "must be a JSON object"),
])
def test_validate_arguments(arguments, problem):
    problems = validate_arguments(SCHEMA, arguments)
    assert (problems == []) if problem is None else any(problem in p for p in problems), problems


def test_calculator_answers_exactly():
    result = call(make_tool("calculator"), {"expression": "123456789 * 987654321 + 1/4"})
    assert result.ok and result.text == "121932631112635269.25"
    assert result.error is None and result.wall_time_s >= 0


def test_calculator_refusal_is_an_observation():
    result = call(make_tool("calculator"), {"expression": "10**10**10"})
    assert not result.ok and result.error == "exception"
    assert result.text.startswith("Error: tool 'calculator' failed") and "digits" in result.text


def test_bad_arguments_are_an_observation():
    result = call(make_tool("calculator"), {"expr": "1+1"})
    assert not result.ok and result.error == "arguments"
    assert "missing required argument 'expression'" in result.text and "unknown argument 'expr'" in result.text


def test_raising_tool_is_an_observation():
    result = call(Raising(), {})
    assert result.error == "exception" and "RuntimeError: boom" in result.text


def test_hanging_tool_times_out():
    result = call(Hanging(), {})
    assert result.error == "timeout" and "timed out after 0.2 s" in result.text


def test_non_text_answer_is_an_observation():
    result = call(NotText(), {})
    assert result.error == "exception" and "returned int" in result.text


def test_python_tool_runs_code_in_the_sandbox():
    tool = PythonTool(limits=SandboxLimits(wall_time_s=20.0, cpu_time_s=1.0))
    printed = call(tool, {"code": "print(sum(i * i for i in range(10)))"})
    assert printed.ok and printed.text == "285"
    failing = call(tool, {"code": "import sys\nprint('partial')\nsys.exit('bad input')"})
    assert failing.ok  # the tool worked; the program failed, and the model reads how
    assert failing.text == "partial\n[stderr]\nbad input\n[exit code 1]"
    looping = call(tool, {"code": "while True:\n    pass"})
    assert looping.text.endswith("[stopped: cpu_time limit]")
    silent = call(tool, {"code": "x = 1"})
    assert silent.text == "[no output]"


def test_python_tool_shortens_long_output():
    tool = PythonTool(limits=SandboxLimits(max_output_bytes=100_000), max_chars=200)
    result = call(tool, {"code": "print('y' * 5000)"})
    assert len(result.text) <= 200 and result.text.endswith("[output truncated]")


def test_many_tool_calls_run_concurrently():
    tool = make_tool("python", max_concurrent=2)

    async def main():
        return await asyncio.gather(*(call_tool(tool, {"code": f"print({i} + 1)"}) for i in range(4)))

    assert [r.text for r in asyncio.run(main())] == ["1", "2", "3", "4"]
