"""Call formats: round trips, every malformed call an error message, and no input that crashes a parser."""

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from infinirl.agents.tool_calls import CALL_FORMATS, ParsedTurn, ToolCall, make_call_format
from infinirl.agents.tools import Tool, make_tool
from infinirl.registry import UnknownNameError


class Search(Tool):
    name = "search"
    description = "look up"
    parameters = {"type": "object", "properties": {"query": {"type": "string"}, "k": {"type": "integer"}},
                  "required": ["query"]}

    async def run(self, query: str, k: int = 3) -> str:
        return query


class Repeat(Tool):
    name = "repeat"
    description = "an integer argument"
    parameters = {"type": "object", "properties": {"times": {"type": "integer"}}, "required": ["times"]}

    async def run(self, times: int) -> str:
        return "x" * times


TOOLS = {"calculator": make_tool("calculator"), "python": make_tool("python"), "search": Search(),
         "repeat": Repeat()}
CALLS = [("calculator", {"expression": "12 * (3 + 4)"}), ("python", {"code": "for i in range(3):\n    print(i)"}),
         ("search", {"query": "who", "k": 2}), ("repeat", {"times": 3})]


def test_registry():
    assert {"hermes", "tags"} <= set(CALL_FORMATS.names())
    with pytest.raises(UnknownNameError):
        make_call_format("xml")


@pytest.mark.parametrize("format_name", ["hermes", "tags"])
@pytest.mark.parametrize("name, arguments", CALLS)
def test_round_trip(format_name, name, arguments):
    fmt = make_call_format(format_name)
    text = "Let me check. " + fmt.format_call(name, arguments, TOOLS) + " trailing"
    parsed = fmt.parse(text, TOOLS)
    assert parsed.errors == ()
    assert [(c.name, c.arguments) for c in parsed.calls] == [(name, arguments)]


@pytest.mark.parametrize("format_name", ["hermes", "tags"])
def test_missing_closing_tag_at_the_end_counts(format_name):
    fmt = make_call_format(format_name)
    closed = fmt.format_call("calculator", {"expression": "1+2"}, TOOLS)
    stop = fmt.stop_strings(TOOLS)
    cut = next(s for s in stop if closed.endswith(s))
    parsed = fmt.parse("I will compute " + closed[: -len(cut)], TOOLS)
    assert [(c.name, c.arguments) for c in parsed.calls] == [("calculator", {"expression": "1+2"})]


def test_hermes_several_calls_and_string_arguments():
    fmt = make_call_format("hermes")
    text = ('<tool_call>{"name": "calculator", "arguments": {"expression": "1+1"}}</tool_call>\n'
            '<tool_call>{"name": "search", "arguments": "{\\"query\\": \\"q\\"}"}</tool_call>')
    parsed = fmt.parse(text, TOOLS)
    assert [c.name for c in parsed.calls] == ["calculator", "search"]
    assert parsed.calls[1].arguments == {"query": "q"}


@pytest.mark.parametrize("body, message", [
    ('{"name": "calculator", "arguments": {"expression": "1+1"', "invalid JSON"),
    ("not json at all", "invalid JSON"),
    ("", "invalid JSON"),
    ('["calculator"]', "must be a JSON object"),
    ('{"arguments": {"expression": "1"}}', 'needs a "name"'),
    ('{"name": 3, "arguments": {}}', 'needs a "name"'),
    ('{"name": "calc", "arguments": {"expression": "1"}}', "unknown tool 'calc'; available tools: calculator"),
    ('{"name": "calculator"}', "missing required argument 'expression'"),
    ('{"name": "calculator", "arguments": {}}', "missing required argument 'expression'"),
    ('{"name": "calculator", "arguments": {"expression": 12}}', "must be of type string"),
    ('{"name": "calculator", "arguments": "{oops"}', '"arguments" is not a JSON object'),
    ('{"name": "calculator", "arguments": [1]}', "must be a JSON object"),
    ('{"name": "search", "arguments": {"query": "q", "k": "3"}}', "'k' must be of type integer"),
    ("[" * 100_000, "invalid JSON"),
    pytest.param('{"name": "calculator", "arguments": "' + "[" * 100_000 + '"}', '"arguments" is not a JSON object',
                 id="deep-arguments-string"),
    pytest.param('{"name": "repeat", "arguments": {"times": ' + "9" * 5000 + "}}",
                 "invalid JSON in <tool_call> (a number too long", id="huge-integer"),
    pytest.param('{"name": "repeat", "arguments": "{\\"times\\": ' + "9" * 5000 + '}"}',
                 '"arguments" is not a JSON object', id="huge-integer-in-arguments-string"),
])
def test_hermes_malformed_calls_are_messages(body, message):
    parsed = make_call_format("hermes").parse(f"<tool_call>{body}</tool_call>", TOOLS)
    assert parsed.calls == () and parsed.has_calls
    assert len(parsed.errors) == 1 and message in parsed.errors[0].message, parsed.errors
    assert len(parsed.errors[0].message) < 600


@pytest.mark.parametrize("text, message", [
    ("<calculator></calculator>", "empty <calculator> call"),
    ("<calculator>  \n </calculator>", "empty <calculator> call"),
    ('<search>{"query": </search>', "expects a JSON object of arguments"),
    ('<search>{"k": 2}</search>', "missing required argument 'query'"),
    ('<search>["q"]</search>', "must be a JSON object"),
    ("<repeat>three</repeat>", "expects a JSON integer"),
    ('<repeat>"3"</repeat>', "'times' must be of type integer"),
    pytest.param("<repeat>" + "[" * 100_000 + "</repeat>", "expects a JSON integer (nested too deeply)",
                 id="deep-sole-argument"),
    pytest.param("<repeat>" + "9" * 5000 + "</repeat>", "expects a JSON integer (a number too long",
                 id="huge-sole-integer"),
    pytest.param('<search>{"query": "q", "k": ' + "9" * 5000 + "}</search>",
                 "expects a JSON object of arguments (a number too long", id="huge-integer-argument"),
    pytest.param("<search>" + "[" * 100_000 + "</search>", "expects a JSON object of arguments (nested too deeply)",
                 id="deep-arguments"),
])
def test_tag_malformed_calls_are_messages(text, message):
    parsed = make_call_format("tags").parse(text, TOOLS)
    assert parsed.calls == () and len(parsed.errors) == 1
    assert message in parsed.errors[0].message, parsed.errors
    assert len(parsed.errors[0].message) < 600


@pytest.mark.parametrize("format_name, bad", [
    ("hermes", '<tool_call>{"name": "calculator", "arguments": "' + "[" * 100_000 + '"}</tool_call>'),
    ("hermes", '<tool_call>{"name": "repeat", "arguments": {"times": ' + "9" * 5000 + "}}</tool_call>"),
    ("tags", "<repeat>" + "[" * 100_000 + "</repeat>"),
    ("tags", "<repeat>" + "9" * 5000 + "</repeat>"),
], ids=["hermes-deep", "hermes-huge-integer", "tags-deep", "tags-huge-integer"])
def test_an_unreadable_call_keeps_the_other_calls_of_its_turn(format_name, bad):
    fmt = make_call_format(format_name)
    good = [fmt.format_call("calculator", {"expression": "1+2"}, TOOLS), fmt.format_call("repeat", {"times": 2}, TOOLS)]
    parsed = fmt.parse(f"{good[0]} then {bad} then {good[1]}", TOOLS)
    assert [(c.name, c.arguments) for c in parsed.calls] == [("calculator", {"expression": "1+2"}),
                                                             ("repeat", {"times": 2})]
    assert len(parsed.errors) == 1
    assert [type(item).__name__ for item in parsed.items] == ["ToolCall", "ToolCallError", "ToolCall"]


def test_items_keep_the_written_order_of_calls_and_errors():
    fmt = make_call_format("hermes")
    text = ('<tool_call>{"name": "calculator", "arguments": {"expression": "1+"}}</tool_call>'
            '<tool_call>{"name": "calc", "arguments": {"expression": "1"}}</tool_call>'
            '<tool_call>{"name": "calculator", "arguments": {"expression": "2+2"}}</tool_call>')
    parsed = fmt.parse(text, TOOLS)
    assert [getattr(item, "name", None) for item in parsed.items] == ["calculator", None, "calculator"]
    assert parsed.calls == (parsed.items[0], parsed.items[2]) and parsed.errors == (parsed.items[1],)
    direct = ParsedTurn(calls=parsed.calls, errors=parsed.errors)  # built without items: calls, then errors
    assert direct.items == (*parsed.calls, *parsed.errors)


def test_text_without_calls():
    for name in ("hermes", "tags"):
        parsed = make_call_format(name).parse("The answer is 42. <b>bold</b> <calc>1</calc>", TOOLS)
        assert parsed == ParsedTurn() and not parsed.has_calls


def test_tag_body_is_dedented_code():
    parsed = make_call_format("tags").parse("<python>\n    x = 2\n    print(x)\n</python>", TOOLS)
    assert parsed.calls == (ToolCall(name="python", arguments={"code": "x = 2\nprint(x)"},
                                     text="<python>\n    x = 2\n    print(x)\n</python>"),)


def test_results_and_stop_strings():
    hermes, tags = make_call_format("hermes"), make_call_format("tags")
    assert hermes.format_results(["42", "Error: x"]) == (
        "<tool_response>\n42\n</tool_response>\n<tool_response>\nError: x\n</tool_response>")
    assert tags.format_results(["42"]) == "<result>\n42\n</result>"
    assert hermes.stop_strings(TOOLS) == ("</tool_call>",)
    assert tags.stop_strings(TOOLS) == ("</calculator>", "</python>", "</repeat>", "</search>")


def test_system_prompts_list_the_tools():
    hermes_prompt = make_call_format("hermes").system_prompt(TOOLS)
    listed = hermes_prompt.split("<tools>\n")[1].split("\n</tools>")[0].splitlines()
    assert [json.loads(line)["function"]["name"] for line in listed] == list(TOOLS)
    tag_prompt = make_call_format("tags").system_prompt(TOOLS)
    assert "<calculator>expression</calculator>" in tag_prompt and "<search>{" in tag_prompt


FRAGMENTS = st.sampled_from(["<tool_call>", "</tool_call>", "<calculator>", "</calculator>", "<search>",
                             "</search>", "{", "}", '"name"', '"arguments"', ":", ",", '"calculator"',
                             '"expression"', '"1+1"', "[", "]", "null", "\n", " ", "\\", '"'])


@settings(max_examples=400, deadline=None)
@given(st.lists(st.one_of(FRAGMENTS, st.text(max_size=8)), max_size=40))
def test_parsers_never_raise(pieces):
    text = "".join(pieces)
    for name in ("hermes", "tags"):
        parsed = make_call_format(name).parse(text, TOOLS)
        assert isinstance(parsed, ParsedTurn)
        for call in parsed.calls:
            assert call.name in TOOLS and call.text in text
