"""Verifiers: gsm8k, reasoning_gym, user functions, format bonus, and never-crash scoring."""

import textwrap

import pytest

from infinirl.tasks.problem import Problem
from infinirl.tasks.reasoning_gym_tasks import ReasoningGymTask, build_eval_set
from infinirl.tasks.verifiers import (
    VERIFIERS,
    RewardResult,
    build_verifier,
    load_function,
    safe_score,
    score_responses,
    summarize_rewards,
)


def numeric_problem(answer: str, verifier: str = "gsm8k") -> Problem:
    return Problem(uid="t/0", prompt="q", answer=answer, verifier=verifier)


# (response, gold, correct under the default "marker" extraction)
GSM8K_CASES = [
    ("3 + 4 = 7\n#### 7", "7", True),
    ("#### 7.0", "7", True),
    ("#### 7.00 dollars", "7", True),
    ("#### $1,000", "1000", True),
    ("#### 1000", "1,000", True),
    ("#### -12", "-12", True),
    ("#### 12", "-12", False),
    ("#### 0.5", "0.50", True),
    ("The answer is 7.", "7", False),  # no marker: not extracted under "marker"
    ("#### seven", "7", False),
    ("#### 6\n...\n#### 7", "7", True),  # the last marker counts
    ("#### 7 (but maybe 8)", "7", True),  # first number after the marker
    ("#### 71", "7", False),
    ("", "7", False),
]


@pytest.mark.parametrize(("response", "gold", "correct"), GSM8K_CASES)
def test_gsm8k_marker_extraction(response, gold, correct):
    result = build_verifier("gsm8k")(response, numeric_problem(gold))
    assert result.correct is correct
    assert result.reward == float(correct)
    assert result.error is None


@pytest.mark.parametrize(
    ("response", "correct"),
    [("The answer is 7.", True), ("7 or 8", False), ("#### 7, checked with 2", False)],
)
def test_gsm8k_last_number_extraction(response, correct):
    assert build_verifier("gsm8k", extraction="last_number")(response, numeric_problem("7")).correct is correct


def test_gsm8k_bad_ground_truth_is_an_error_not_a_crash():
    result = safe_score("#### 3", numeric_problem("three"))
    assert result.reward == 0.0 and not result.correct
    assert "three" in result.error


@pytest.fixture(scope="module")
def chain_sum_problems():
    task = ReasoningGymTask("chain_sum", {"min_terms": 2, "max_terms": 2, "min_digits": 2, "max_digits": 2})
    return build_eval_set(task, size=5, seed=3)


def test_reasoning_gym_verifier_uses_the_task_scorer(chain_sum_problems):
    for problem in chain_sum_problems:
        answer = problem.answer
        assert safe_score(f"#### {answer}", problem).correct
        assert safe_score(f"work...\n#### The result is {answer}.", problem).correct
        assert safe_score(f"{problem.metadata['entry']['metadata']['expression']} = {answer}", problem).correct
        assert safe_score(f"\\boxed{{{answer}}}", problem).correct
        wrong = safe_score(f"#### {int(answer) + 1}", problem)
        assert not wrong.correct and wrong.reward == 0.0 and wrong.error is None


def test_reasoning_gym_partial_credit_is_opt_in(chain_sum_problems):
    problem = chain_sum_problems[0]
    padded = f"#### {problem.answer} 0"  # reasoning-gym gives substring partial credit here
    assert safe_score(padded, problem).reward == 0.0
    partial = build_verifier("reasoning_gym", partial_credit=True)(padded, problem)
    assert 0.0 < partial.reward < 1.0 and not partial.correct


def test_reasoning_gym_without_metadata_reports_how_to_build_problems():
    result = safe_score("#### 3", numeric_problem("3", verifier="reasoning_gym"))
    assert result.reward == 0.0 and "build_eval_set" in result.error


@pytest.mark.parametrize(
    ("response", "gold", "correct"),
    [
        ("#### Step 1: Read\n...\n#### Step 2: Compute\nThe result is 99.", "2", False),
        ("#### Final Answer\n#### 42", "42", True),
        ("#### \u22125", "5", False),
        ("#### \u22125", "-5", True),
        ("#### 3/4", "3", False),
        ("#### 1e3", "1", False),
        ("#### 1e3", "1000", True),
        ("#### 1,2345", "1234", False),
        ("#### 2.5e2", "250", True),
    ],
)
def test_gsm8k_reads_whole_numbers_and_not_headings(response, gold, correct):
    assert build_verifier("gsm8k")(response, numeric_problem(gold)).correct is correct


def test_math_verifier_skips_a_heading_marker():
    problem = Problem(uid="m/0", prompt="q", answer="42", verifier="math")
    assert safe_score("#### Final Answer\n\nThe answer is 42", problem).correct
    assert not safe_score("#### Step 1: Read\n...\n#### Step 42: Compute\nThe result is 99.", problem).correct


def test_reasoning_gym_headings_and_guesses(chain_sum_problems):
    for problem in [p for p in chain_sum_problems if int(p.answer) > 0]:  # a step number is positive
        answer = int(problem.answer)
        assert safe_score(f"#### Final Answer\n\\boxed{{{answer}}}", problem).correct
        steps = f"#### Step 1: Read\n...\n#### Step {answer}: Compute\nThe result is {answer + 57}."
        assert not safe_score(steps, problem).correct
        assert not safe_score(f"#### {answer + 1} or {answer}", problem).correct  # two guesses
        assert safe_score(f"#### It is {answer} in total", problem).correct


# --- never crash -----------------------------------------------------------------------------


def test_raising_verifier_gives_error_and_zero_reward():
    def broken(response, problem):
        raise RuntimeError("checker exploded")

    result = safe_score("#### 1", numeric_problem("1"), verifier=broken)
    assert result == RewardResult(0.0, False, error="RuntimeError: checker exploded")


def test_unknown_verifier_name_is_reported_per_sample():
    result = safe_score("#### 1", numeric_problem("1", verifier="nonexistent"))
    assert result.reward == 0.0 and "nonexistent" in result.error and "gsm8k" in result.error


def test_error_count_is_reported_in_summary():
    problems = [numeric_problem("1"), numeric_problem("x"), numeric_problem("2")]
    results = score_responses(["#### 1", "#### 1", "#### 3"], problems)
    summary = summarize_rewards(results)
    assert summary["verifier_errors"] == 1.0
    assert summary["accuracy"] == pytest.approx(1 / 3)
    assert summary["reward_mean"] == pytest.approx(1 / 3)
    assert summary["answer_found_mean"] == 1.0  # errored sample has no metrics, others found one


def test_score_responses_rejects_misaligned_lists():
    with pytest.raises(ValueError, match="2 responses but 1 problems"):
        score_responses(["a", "b"], [numeric_problem("1")])


def test_bad_verifier_options_name_the_verifier():
    with pytest.raises(TypeError, match="'gsm8k'"):
        build_verifier("gsm8k", extractoin="marker")
    with pytest.raises(KeyError, match="boxed"):
        build_verifier("gsm8k", extraction="guess")


def test_registry_holds_the_documented_verifiers():
    assert {"math", "gsm8k", "reasoning_gym"} <= set(VERIFIERS.names())


# --- the reward worker: each problem by its own verifier ----------------------------------------


def test_each_problem_is_scored_by_the_verifier_it_names(chain_sum_problems):
    from concurrent.futures import ThreadPoolExecutor

    from infinirl.components.reward import ProblemVerifiers

    # The configured verifier is the reasoning_gym default, as a run on task.source=dataset
    # task.name=gsm8k has: the gsm8k rows name gsm8k, which must score them.
    verifiers = ProblemVerifiers("reasoning_gym", format_bonus=0.5)
    gym = chain_sum_problems[0]
    unnamed = Problem(uid="t/1", prompt="q", answer="7", verifier="")
    problems = [numeric_problem("7"), numeric_problem("7"), gym, unnamed]
    texts = ["#### 7", "#### 8", f"#### {gym.answer}", "#### 7"]
    with ThreadPoolExecutor(2) as pool:
        scored = verifiers.score(texts, problems, pool)
        unknown = verifiers.score(["#### 7"], [numeric_problem("7", verifier="nonexistent")], pool)
    assert [s.error for s in scored[:3]] == [None, None, None]
    assert [s.correct for s in scored[:3]] == [True, False, True]
    assert scored[0].reward == pytest.approx(1.5) and scored[1].reward == pytest.approx(0.5)  # the format bonus too
    assert "reasoning_gym" in scored[3].error  # no name: the configured verifier (which needs the gym's entry)
    assert verifiers.get("gsm8k") is verifiers.get("gsm8k")  # built once per name
    assert unknown[0].reward == 0.0 and "nonexistent" in unknown[0].error  # a counted per-sample error
    with pytest.raises(KeyError, match="nonexistent"):  # a bad configured name fails at start
        ProblemVerifiers("nonexistent")


def test_reward_worker_scores_decoded_responses_by_their_problems_verifiers(tiny_byte_llama, tmp_path):
    from infinirl.components.reward import RewardWorker
    from infinirl.engines.base import GenerationResult

    _, tokenizer = tiny_byte_llama
    tokenizer.save_pretrained(tmp_path)
    worker = RewardWorker(str(tmp_path), "reasoning_gym")
    problems = [numeric_problem("7"), Problem(uid="m/0", prompt="q", answer="\\frac{1}{2}", verifier="math")]
    results = [GenerationResult(prompt_ids=[1], response_ids=tokenizer.encode(text, add_special_tokens=False),
                                response_logprobs=[], finish_reason="stop", weight_version=0)
               for text in ("#### 7", "\\boxed{0.5}")]
    scored = worker.score(results, problems)
    assert [(s.correct, s.error) for s in scored] == [(True, None), (True, None)]


# --- format bonus ------------------------------------------------------------------------------


def test_format_bonus_is_off_by_default_and_adds_when_enabled():
    problem = numeric_problem("5")
    plain = build_verifier("gsm8k", extraction="last_number")
    with_bonus = build_verifier("gsm8k", extraction="last_number", format_bonus=0.1)
    assert plain("so 5", problem).reward == 1.0
    assert with_bonus("so 5", problem).reward == 1.0
    assert with_bonus("#### 5", problem).reward == pytest.approx(1.1)
    wrong_but_formatted = with_bonus("#### 4", problem)
    assert wrong_but_formatted.reward == pytest.approx(0.1) and not wrong_but_formatted.correct
    assert wrong_but_formatted.metrics["format_followed"] == 1.0


def test_format_bonus_for_boxed_answers():
    verifier = build_verifier("math", format_bonus=0.2, answer_format="boxed")
    problem = Problem(uid="m/0", prompt="q", answer="\\frac{1}{2}", verifier="math")
    assert verifier("\\boxed{0.5}", problem).reward == pytest.approx(1.2)
    assert verifier("it is 0.5", problem).reward == pytest.approx(1.0)
    with pytest.raises(KeyError, match="boxed"):
        build_verifier("math", format_bonus=0.2, answer_format="bold")


def test_format_bonus_needs_an_answer_the_verifier_found():
    with_bonus = build_verifier("gsm8k", format_bonus=0.1)
    problem = numeric_problem("5")
    for unanswered in ("#### banana", "#### ?"):  # the marker, but no number after it
        result = with_bonus(unanswered, problem)
        assert result.reward == 0.0 and result.metrics["format_followed"] == 0.0


def test_the_reward_worker_checks_the_tasks_answer_format():
    from concurrent.futures import ThreadPoolExecutor

    from infinirl.components.reward import ProblemVerifiers

    # A math500-like task asks for \boxed{}: a boxed answer earns the bonus, one after '####' does not.
    verifiers = ProblemVerifiers("math", format_bonus=0.5, answer_format="boxed")
    problem = Problem(uid="m/0", prompt="q", answer="7", verifier="math")
    with ThreadPoolExecutor(1) as pool:
        boxed, marked = verifiers.score(["\\boxed{7}", "#### 7"], [problem, problem], pool)
    assert (boxed.reward, marked.reward) == (pytest.approx(1.5), pytest.approx(1.0))
    assert boxed.correct and marked.correct


# --- user functions by dotted path -------------------------------------------------------------


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    (tmp_path / "my_rewards.py").write_text(
        textwrap.dedent(
            """
            NOT_CALLABLE = 3

            def length_penalty(response, problem):
                return 1.0 if problem.answer in response else -0.5

            def with_metrics(response, problem):
                return {"reward": 0.5, "correct": True, "length": len(response)}

            def missing_reward(response, problem):
                return {"score": 1.0}

            def wrong_type(response, problem):
                return "1.0"

            def raises(response, problem):
                raise ValueError("user bug")

            def not_a_number(response, problem):
                return float("nan")

            def infinite(response, problem):
                return {"reward": float("inf"), "correct": True}

            class Scorers:
                @staticmethod
                def nested(response, problem):
                    return 2.0
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "my_rewards"


def test_user_float_function(user_module):
    verifier = build_verifier(f"{user_module}:length_penalty")
    assert verifier("the answer 9", numeric_problem("9")) == RewardResult(1.0, True)
    assert verifier("nothing", numeric_problem("9")) == RewardResult(-0.5, False)


def test_user_dict_function_keeps_extra_metrics(user_module):
    result = build_verifier(f"{user_module}:with_metrics")("abcd", numeric_problem("1"))
    assert result == RewardResult(0.5, True, metrics={"length": 4.0})


def test_user_nested_attribute(user_module):
    assert build_verifier(f"{user_module}:Scorers.nested")("x", numeric_problem("1")).reward == 2.0


def test_problem_can_name_a_user_function(user_module):
    assert safe_score("9", numeric_problem("9", verifier=f"{user_module}:length_penalty")).reward == 1.0


@pytest.mark.parametrize(
    ("function", "message"),
    [("missing_reward", "without 'reward'; keys: \\['score'\\]"), ("wrong_type", "returned str"),
     ("raises", "user bug"), ("not_a_number", "not a finite number"), ("infinite", "not a finite number")],
)
def test_user_function_failures_become_sample_errors(user_module, function, message):
    result = safe_score("x", numeric_problem("1", verifier=f"{user_module}:{function}"))
    assert result.reward == 0.0 and not result.correct
    assert result.error is not None
    import re

    assert re.search(message, result.error)
    assert summarize_rewards([result])["verifier_errors"] == 1.0


@pytest.mark.parametrize(
    ("path", "error", "message"),
    [
        ("my_rewards.length_penalty", ValueError, "package.module:function"),
        ("no_such_module_xyz:f", ImportError, "cannot import module 'no_such_module_xyz'"),
        ("my_rewards:absent", AttributeError, "has no attribute 'absent'"),
        ("my_rewards:NOT_CALLABLE", TypeError, "not a callable"),
        (":f", ValueError, "package.module:function"),
    ],
)
def test_load_function_errors_name_the_bad_part(user_module, path, error, message):
    with pytest.raises(error, match=message):
        load_function(path)
