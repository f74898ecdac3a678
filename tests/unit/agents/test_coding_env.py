"""The code_runner environment: turns run in the sandbox against the visible tests; a
write-run-fix trajectory through the real agent loop, scored by the code_tests verifier."""

import pytest

from infinirl.agents.coding.env import CodeRunnerEnv
from infinirl.agents.coding.verifier import CodeTestsVerifier
from infinirl.agents.loop import AgentBudget, AgentConfig, AgentRollout
from infinirl.agents.registered import resolve_agent_env
from infinirl.components.reward import sampled_ids
from infinirl.config import ConfigError
from infinirl.engines.base import SamplingParams
from infinirl.models.hf_causal_lm import tiny_causal_lm
from infinirl.tasks.code_tasks import FunctionTaskOptions, function_problem
from tests.unit.agents.scripted import ScriptedEngine

LIMITS = {"wall_time_s": 5.0, "cpu_time_s": 1.0}
PROBLEM = function_problem(FunctionTaskOptions(families=("scale_and_shift",)), 0, 0, "train")
RIGHT = PROBLEM.answer  # the reference solution
WRONG = RIGHT.replace("return x *", "return 1 + x *")


def turn(code, after=""):
    return f"Let me write it.\n```python\n{code}```\n{after}"


def env_for(problem=PROBLEM, **options):
    env = CodeRunnerEnv(limits=LIMITS, **options)
    env.reset(problem)
    return env


def test_passing_code_ends_the_trajectory():
    step = env_for().step(turn(RIGHT))
    assert step.done and step.info["code_ok"] == 1.0 and step.info["visible_tests_passed"] == 1.0
    assert step.info["sandbox_namespaces"] == 1.0


def test_failing_code_gets_the_visible_failures_with_the_values_returned():
    step = env_for().step(turn(WRONG))
    assert not step.done and not step.error
    assert step.observation.startswith("\nResult:\n0/2 tests passed.\nFailed: assert scale_and_shift(")
    assert "(got " in step.observation and step.info["visible_tests_passed"] == 0.0
    hidden = PROBLEM.metadata["tests"].splitlines()[-1].strip().replace("candidate", "scale_and_shift")
    assert hidden.split("==")[0] not in step.observation  # only the visible tests run


def test_code_that_breaks_or_runs_away_is_an_observation_not_a_crash():
    broken = env_for().step(turn("def scale_and_shift(x) return x\n"))
    assert not broken.done and "The code did not run: " in broken.observation and "SyntaxError" in broken.observation
    endless = env_for().step(turn("def scale_and_shift(x):\n    while True:\n        pass\n"))
    assert not endless.done and "limit" in endless.observation


def test_all_tests_as_feedback_and_the_observation_template():
    env = env_for(feedback="all", observation_template="<|im_end|>\n<|im_start|>user\n{feedback}<|im_end|>\n")
    step = env.step(turn(WRONG))
    total = PROBLEM.metadata["tests"].count("assert")
    assert f"0/{total} tests passed." in step.observation and step.observation.startswith("<|im_end|>\n<|im_start|>")


def test_without_a_problem_the_code_runs_as_a_program():
    env = env_for(problem=None)
    printed = env.step(turn("print(6 * 7)\n"))
    assert printed.done and printed.info["code_ok"] == 1.0
    failing = env.step(turn("raise ValueError('nope')\n"))
    assert not failing.done and "ValueError: nope" in failing.observation and "[exit code 1]" in failing.observation
    assert not env_for(problem=None, stop_when_passing=False).step(turn("print(1)\n")).done


def test_turns_without_code_are_answers_and_an_opening_fence_continues_the_turn():
    env = env_for()
    opening = env.step("I will write it:\n```\n")  # the stop string matched a bare fence opening a block
    assert not opening.done and opening.observation == ""
    assert env.step("Multiply x, then add.").done
    assert env.step("```text\nsome output\n```\n").done


def test_bad_options_are_refused_and_the_env_is_registered():
    assert resolve_agent_env("code_runner") is CodeRunnerEnv
    with pytest.raises(ValueError, match="feedback"):
        CodeRunnerEnv(feedback="some")
    with pytest.raises(ValueError, match="run_answers='yes': use true or false"):
        CodeRunnerEnv(run_answers="yes")
    with pytest.raises(ValueError, match="placeholder"):
        CodeRunnerEnv(observation_template="no slot")
    with pytest.raises(ConfigError, match="env_options for env 'code_runner'"):
        AgentConfig(env="code_runner", env_options={"limits": {"wall": 1}}).check("rollout.agent")
    AgentConfig(env="code_runner", env_options={"feedback": "all"}).check("rollout.agent")


def test_write_run_fix_through_the_agent_loop_and_the_verifier_scores_the_last_code():
    _, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
    engine = ScriptedEngine(tokenizer, [turn(WRONG), turn(RIGHT, "Done.")])
    rollout = AgentRollout(engine, tokenizer, lambda: CodeRunnerEnv(limits=LIMITS), AgentBudget(max_turns=3))
    [result] = rollout.generate([[1, 2, 3]], SamplingParams(n=1, max_new_tokens=400), problems=[PROBLEM])
    stats = result.extra["agent"]
    assert stats["turns"] == 2 and stats["env_steps"] == 2 and stats["end"] == "answer"
    assert stats["totals"]["code_runs"] == 2.0 and stats["totals"]["code_ok"] == 1.0
    model_text = tokenizer.decode(sampled_ids(result))
    assert "Result:" not in model_text  # the environment's text is not the model's
    verifier = CodeTestsVerifier(limits=LIMITS)
    assert verifier(model_text, PROBLEM).correct  # the fixed code, written last
    assert not verifier(turn(WRONG), PROBLEM).correct


CHAT = "<|im_end|>\n<|im_start|>user\n{feedback}<|im_end|>\n<|im_start|>assistant\n"


def answer(code):
    """A turn that ends right after the closing fence with the end-of-turn token (no stop string)."""
    return f"Here it is.\n```python\n{code}```<|im_end|>"


def test_run_answers_runs_the_code_of_a_turn_ended_by_eos_without_repeating_the_eos():
    env = env_for(run_answers=True, observation_template=CHAT)
    assert env.step_answer_turns and not env_for().step_answer_turns
    failing = env.step(answer(WRONG))
    assert not failing.done and failing.info["answer_runs"] == 1
    assert failing.observation.startswith("\n<|im_start|>user\n0/2 tests passed.")
    assert env.step(answer(RIGHT)).done
    handed = env.step(turn(WRONG))  # a turn ended on the stop string keeps the whole template
    assert handed.observation.startswith("<|im_end|>\n<|im_start|>user") and "answer_runs" not in handed.info


@pytest.mark.parametrize(("run_answers", "max_turns", "turns", "env_steps"),
                         [(True, 3, 2, 2), (False, 3, 1, 0), (True, 1, 1, 0)])
def test_an_eos_ended_turn_gets_feedback_only_with_run_answers_and_a_turn_left(run_answers, max_turns, turns,
                                                                              env_steps):
    _, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
    engine = ScriptedEngine(tokenizer, [answer(WRONG), answer(RIGHT)])
    rollout = AgentRollout(engine, tokenizer,
                           lambda: CodeRunnerEnv(limits=LIMITS, run_answers=run_answers, observation_template=CHAT),
                           AgentBudget(max_turns=max_turns))
    [result] = rollout.generate([[1, 2, 3]], SamplingParams(n=1, max_new_tokens=400), problems=[PROBLEM])
    stats = result.extra["agent"]
    assert (stats["turns"], stats["env_steps"], stats["end"]) == (turns, env_steps, "answer")
    text = tokenizer.decode(result.response_ids)
    assert text.count("<|im_end|>") == 2 * (turns - 1) + 1  # the model's EOS, then the template's own closing one
    assert CodeTestsVerifier(limits=LIMITS)(tokenizer.decode(sampled_ids(result)), PROBLEM).correct == (turns == 2)


def test_feedback_over_the_budget_is_cut_inside_the_template_which_still_hands_the_turn_back():
    """The template's end (the user turn's close, the assistant's opening) must survive the cut,
    or the model's next turn would be written, and trained on, inside the user's message."""
    _, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
    template = CHAT.replace("{feedback}", "I ran it:\n{feedback}\nFix it.")
    wrapper = len(tokenizer.encode(template.replace("{feedback}", ""), add_special_tokens=False))
    engine = ScriptedEngine(tokenizer, [turn(WRONG), turn(RIGHT, "Done.")])
    rollout = AgentRollout(engine, tokenizer, lambda: CodeRunnerEnv(limits=LIMITS, observation_template=template),
                           AgentBudget(max_turns=2, max_observation_tokens=wrapper + 40))
    [result] = rollout.generate([[1, 2, 3]], SamplingParams(n=1, max_new_tokens=400), problems=[PROBLEM])
    observation = [i for i, m in zip(result.response_ids, result.response_mask) if not m]
    assert len(observation) == wrapper + 40
    text = tokenizer.decode(observation)
    assert text.startswith("<|im_end|>\n<|im_start|>user\nI ran it:\n0/2 tests passed.")
    assert text.endswith(" ...[truncated]\nFix it.<|im_end|>\n<|im_start|>assistant\n")
    assert result.extra["agent"]["turns"] == 2


def test_an_answer_whose_feedback_has_no_room_left_ends_as_an_answer_not_cut_off():
    """Under run_answers, an EOS-ended turn whose feedback does not fit is still the model's answer:
    not counted as truncated (truncated_reward: zero would zero its reward)."""
    _, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
    engine = ScriptedEngine(tokenizer, [answer(WRONG)])
    length = len(tokenizer.encode(answer(WRONG), add_special_tokens=False))
    rollout = AgentRollout(engine, tokenizer,
                           lambda: CodeRunnerEnv(limits=LIMITS, run_answers=True, observation_template=CHAT),
                           AgentBudget(max_turns=3, max_response_tokens=length + 20))
    [result] = rollout.generate([[1, 2, 3]], SamplingParams(n=1, max_new_tokens=400), problems=[PROBLEM])
    stats = result.extra["agent"]
    assert (stats["turns"], stats["env_steps"], stats["end"], result.finish_reason) == (1, 1, "answer", "stop")
    assert stats["totals"]["answer_runs"] == 1.0
