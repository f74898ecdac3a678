"""The tool-calling agent environment and the agent config's checks."""

import asyncio
import json
import re
import time

import pytest

from infinirl.agents.loop import AgentBudget, AgentRollout
from infinirl.agents.registered import resolve_agent_env
from infinirl.agents.tool_env import ToolEnv
from infinirl.agents.tools import TOOLS, Tool
from infinirl.config import ConfigError, to_dataclass
from infinirl.engines.base import SamplingParams
from infinirl.runners.reasoning_config import ReasoningConfig
from tests.unit.agents.scripted import ScriptedEngine

CALCULATOR_PROMPT = {"system_prompt": "Write <calculator>expression</calculator> to use the calculator."}


@TOOLS.register("sleeper")
class SleeperTool(Tool):
    """Blocks a thread for the given seconds: work that a timeout cannot interrupt."""

    name = "sleeper"
    description = "Sleeps."
    parameters = {"type": "object", "properties": {"seconds": {"type": "string"}}, "required": ["seconds"]}

    def __init__(self, timeout_s: float = 10.0):
        self.timeout_s = timeout_s

    async def run(self, seconds: str) -> str:
        await asyncio.to_thread(time.sleep, float(seconds))
        return "awake"


@pytest.fixture(scope="module")
def smollm2_tokenizer():
    from transformers import AutoTokenizer

    from infinirl.models.smollm2 import ensure_converted

    return AutoTokenizer.from_pretrained(ensure_converted())


def test_a_call_runs_and_its_result_comes_back():
    env = ToolEnv(tools=["calculator"])
    assert env.stop_strings == ("</calculator>",)
    step = env.step("I will compute <calculator>378 * 937</calculator><")
    assert not step.done and not step.error and "354186" in step.observation
    assert step.info["tool_calls"] == 1


def test_a_turn_without_a_call_is_the_answer():
    assert ToolEnv().step("The answer is 354186.").done


def test_malformed_calls_and_tool_errors_are_observations_not_crashes():
    env = ToolEnv(tools=["calculator"])
    step = env.step("<calculator>378 * </calculator>")
    assert step.error and not step.done and "Error" in step.observation
    empty = env.step("<calculator></calculator>")
    assert empty.error and "empty" in empty.observation


def test_calls_beyond_the_per_turn_limit_are_refused_with_a_message():
    env = ToolEnv(tools=["calculator"], max_calls_per_turn=1)
    step = env.step("<calculator>1+1</calculator><calculator>2+2</calculator>")
    assert step.error and "2" in step.observation and "at most 1 tool calls" in step.observation


def test_the_ith_response_answers_the_ith_call():
    env = ToolEnv(tools=["calculator"], call_format="hermes", max_calls_per_turn=3)  # "1+" counts: it runs
    calls = [{"name": "calculator", "arguments": {"expression": "1+"}},
             {"name": "calc", "arguments": {"expression": "1"}},
             {"name": "calculator", "arguments": {"expression": "2+2"}},
             {"name": "calculator", "arguments": {"expression": "3+3"}},
             {"name": "calculator", "arguments": {"expression": "4+4"}}]
    turn = "".join(f"<tool_call>{json.dumps(call)}</tool_call>" for call in calls)
    step = env.step(turn)
    responses = re.findall(r"<tool_response>\n(.*?)\n</tool_response>", step.observation, re.DOTALL)
    assert len(responses) == len(calls), step.observation
    assert responses[0].startswith("Error") and "unknown tool 'calc'" in responses[1]
    assert responses[2:4] == ["4", "6"]
    assert "at most 3 tool calls" in responses[4] and "'calculator' was not run" in responses[4]
    assert step.error and step.info["tool_calls"] == 3


def test_hermes_format():
    env = ToolEnv(tools=["calculator"], call_format="hermes")
    step = env.step('<tool_call>{"name": "calculator", "arguments": {"expression": "6*7"}}</tool_call>')
    assert "42" in step.observation and not step.error


def test_bad_options_are_one_line_errors():
    with pytest.raises(ValueError, match="at least one"):
        ToolEnv(tools=[])
    with pytest.raises(ValueError, match="not in tools"):
        ToolEnv(tools=["calculator"], tool_options={"python": {}})


def test_envs_resolve_by_name_or_dotted_path():
    assert resolve_agent_env("tools") is ToolEnv
    assert resolve_agent_env("infinirl.agents.toy_envs:EchoEnv").__name__ == "EchoEnv"
    with pytest.raises(ImportError, match="no_such_module"):
        resolve_agent_env("no_such_module:Env")


def _cfg(agent, task=None):
    return to_dataclass(ReasoningConfig, {"rollout": {"agent": agent}, "task": task or CALCULATOR_PROMPT})


@pytest.mark.parametrize("agent, message", [
    ({"env": "nope"}, "rollout.agent.env='nope' is not registered"),
    ({"env": "tools", "env_options": {"tools": ["abacus"]}}, "rollout.agent.env_options"),
    ({"env": "tools", "env_options": {"colour": 1}}, "rollout.agent.env_options"),
    ({"env": "missing.module:Env"}, "rollout.agent.env: agent environment"),
])
def test_config_refuses_bad_agents_before_any_worker(agent, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        _cfg(agent)


def test_config_bounds_are_checked_when_built():
    with pytest.raises(ConfigError, match="max_turns"):
        _cfg({"max_turns": 0})


def test_a_tool_past_its_timeout_does_not_hold_the_step():
    """Work a tool handed to a thread runs on after its timeout, but nothing waits for it."""
    env = ToolEnv(tools=["sleeper"], tool_options={"sleeper": {"timeout_s": 0.3}})
    try:
        start = time.monotonic()
        step = env.step("<sleeper>3</sleeper>")
        elapsed = time.monotonic() - start
        assert step.error and "timed out after 0.3 s" in step.observation
        assert elapsed < 1.5, f"the step took {elapsed:.1f} s"
        assert "awake" in env.step("<sleeper>0</sleeper>").observation  # the environment goes on
    finally:
        env.close()


def test_a_token_running_past_the_call_is_not_written_twice(smollm2_tokenizer):
    """SmolLM2 writes the worked example's ``</calculator><result>`` as ``... ator >< result``: a
    model copying it completes the stop string with ``><``. The observation then starts after that
    ``<``, and the trajectory's ids are exactly the worked example's."""
    tokenizer = smollm2_tokenizer
    example = tokenizer.encode("<calculator>12 + 34</calculator><result>\n46\n</result>\n46", add_special_tokens=False)
    call = tokenizer.encode("<calculator>12 + 34</calculator><", add_special_tokens=False)
    assert tokenizer.decode(call[-1:]) == "><" and example[:len(call)] == call
    result_ids = len(tokenizer.encode("result>\n46\n</result>", add_special_tokens=False))
    engine = ScriptedEngine(tokenizer, [call, example[len(call) + result_ids:]])  # then "\n46"
    rollout = AgentRollout(engine, tokenizer, lambda: ToolEnv(tools=["calculator"]), AgentBudget(max_turns=2))
    [result] = rollout.generate([[1, 2, 3]], SamplingParams(n=1, max_new_tokens=32))
    assert tokenizer.decode(result.response_ids) == "<calculator>12 + 34</calculator><result>\n46\n</result>\n46"
    assert result.response_ids == example
    assert result.response_mask == [1] * len(call) + [0] * result_ids + [1] * (len(example) - len(call) - result_ids)


def test_a_long_result_is_cut_inside_its_tags(smollm2_tokenizer):
    """Over max_observation_tokens, the tool's text is cut; the closing tag (and the template's end)
    is kept, so the model's next turn starts after the result, not inside it."""
    tokenizer = smollm2_tokenizer
    engine = ScriptedEngine(tokenizer, ["<calculator>9**3000</calculator>", "done"])
    rollout = AgentRollout(engine, tokenizer, lambda: ToolEnv(tools=["calculator"], observation_template="{results}\n"),
                           AgentBudget(max_turns=2, max_observation_tokens=24))
    [result] = rollout.generate([[1, 2, 3]], SamplingParams(n=1, max_new_tokens=32))
    observation = [i for i, m in zip(result.response_ids, result.response_mask) if not m]
    assert len(observation) == 24
    text = tokenizer.decode(observation)
    assert text.startswith("<result>\n5339840906") and text.endswith(" ...[truncated]\n</result>\n")
    # several calls: each result is cut, each block closed
    step = ToolEnv(tools=["calculator"]).step("<calculator>9**3000</calculator><calculator>8**3000</calculator>")
    kept = [text for text, cuttable in step.parts if not cuttable]
    assert kept == ["<result>\n", "\n</result>", "\n<result>\n", "\n</result>"]


def test_hermes_results_come_in_a_user_turn_as_qwens_template_writes_them():
    env = ToolEnv(tools=["calculator"], call_format="hermes")
    step = env.step('<tool_call>\n{"name": "calculator", "arguments": {"expression": "6*7"}}\n</tool_call>')
    assert step.observation == ("<|im_end|>\n<|im_start|>user\n<tool_response>\n42\n</tool_response><|im_end|>\n"
                                "<|im_start|>assistant\n")
    own = ToolEnv(tools=["calculator"], call_format="hermes", observation_template="<|im_start|>tool\n{results}|")
    assert own.step('<tool_call>{"name": "calculator", "arguments": {"expression": "1"}}</tool_call>').observation \
        == "<|im_start|>tool\n<tool_response>\n1\n</tool_response>|"
    assert ToolEnv(tools=["calculator"]).step("<calculator>1</calculator>").observation == "<result>\n1\n</result>"
    with pytest.raises(ValueError, match="no {results} placeholder"):
        ToolEnv(observation_template="<result>")


def test_config_refuses_tools_the_prompt_never_names():
    with pytest.raises(ConfigError, match=r"task.system_prompt \(with task.few_shot\) for rollout.agent.env='tools': "
                                          r"never name the tool\(s\) python.*You can use tools"):
        _cfg({"env": "tools", "env_options": {"tools": ["calculator", "python"]}})
    with pytest.raises(ConfigError, match="never name the tool"):
        _cfg({"env": "tools"}, task={"system_prompt": None})
    _cfg({"env": "tools"})
    _cfg({"env": "tools"}, task={"few_shot": [{"user": "1+1?", "assistant": "<calculator>1+1</calculator>"}]})
