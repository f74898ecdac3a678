"""reasoning-gym tasks: held-out disjointness, problem-space size, exact resume."""

import pytest
import reasoning_gym

from infinirl.tasks.problem import normalize_question
from infinirl.tasks.reasoning_gym_tasks import (
    CHUNK,
    ReasoningGymStream,
    ReasoningGymTask,
    build_eval_set,
    count_distinct_questions,
    generate_entry,
)
from infinirl.tasks.verifiers import safe_score

ONE_DIGIT_PAIRS = ReasoningGymTask("chain_sum", {"min_terms": 2, "max_terms": 2, "min_digits": 1, "max_digits": 1})
DEFAULT_MAIN_TASK = ReasoningGymTask("chain_sum", {"min_terms": 2, "max_terms": 2, "min_digits": 1, "max_digits": 2})


def chain_sum_space_size(min_terms, max_terms, min_digits, max_digits):
    """Reference count of distinct chain_sum questions: operand choices times operator choices.

    d-digit operands range over 10 values for d=1 (0..9) and 9*10**(d-1) otherwise.
    """
    total = 0
    for terms in range(min_terms, max_terms + 1):
        for digits in range(min_digits, max_digits + 1):
            operands = 10 if digits == 1 else 9 * 10 ** (digits - 1)
            total += operands**terms * 2 ** (terms - 1)
    return total


def question(problem):
    return normalize_question(problem.metadata["entry"]["question"])


def test_problem_space_of_one_digit_pairs_is_exhausted_by_sampling():
    assert chain_sum_space_size(2, 2, 1, 1) == 200
    assert count_distinct_questions(ONE_DIGIT_PAIRS, draws=4000) == 200


def test_default_task_space_is_large():
    assert chain_sum_space_size(2, 2, 1, 2) == 16_400
    # Half the draws use 1-digit operands (only 200 questions), so distinct counts lag draws.
    assert 1000 < count_distinct_questions(DEFAULT_MAIN_TASK, draws=2000) < 1400


def test_eval_set_is_distinct_and_deterministic():
    first = build_eval_set(DEFAULT_MAIN_TASK, size=50, seed=5)
    again = build_eval_set(DEFAULT_MAIN_TASK, size=50, seed=5)
    assert [p.uid for p in first] == [p.uid for p in again]
    assert len({question(p) for p in first}) == 50
    assert all(safe_score(f"#### {p.answer}", p).correct for p in first)


def test_no_eval_problem_appears_in_a_long_train_stream():
    """Eval covers half of a 200-question space; 3000 train draws must hit exactly the other half."""
    eval_set = build_eval_set(ONE_DIGIT_PAIRS, size=100, seed=11)
    stream = ReasoningGymStream(ONE_DIGIT_PAIRS, seed=0, exclude=eval_set)
    train_questions = {question(p) for p in stream.next_batch(3000)}
    eval_questions = {question(p) for p in eval_set}
    assert train_questions.isdisjoint(eval_questions)
    assert len(train_questions) == 100  # everything not held out is still reachable
    assert stream.skipped > 0  # the exclusion actually fired


def test_exclusion_accepts_raw_question_texts():
    first = generate_entry(ONE_DIGIT_PAIRS, seed=0, index=0)["question"]
    stream = ReasoningGymStream(ONE_DIGIT_PAIRS, seed=0, exclude=["  " + first.upper() + " "])
    assert all(question(p) != normalize_question(first) for p in stream.next_batch(200))


def test_stream_resume_continues_exactly():
    eval_set = build_eval_set(DEFAULT_MAIN_TASK, size=20)
    stream = ReasoningGymStream(DEFAULT_MAIN_TASK, seed=4, exclude=eval_set)
    stream.next_batch(10)
    state = stream.state_dict()
    expected = stream.next_batch(5)
    restored = ReasoningGymStream(DEFAULT_MAIN_TASK, seed=4, exclude=eval_set)
    restored.load_state_dict(state)
    assert restored.next_batch(5) == expected


def test_stream_refuses_a_checkpoint_from_another_config():
    state = ReasoningGymStream(DEFAULT_MAIN_TASK, seed=4).state_dict()
    with pytest.raises(ValueError, match="seed"):
        ReasoningGymStream(DEFAULT_MAIN_TASK, seed=5).load_state_dict(state)
    with pytest.raises(ValueError, match="config"):
        ReasoningGymStream(ONE_DIGIT_PAIRS, seed=4).load_state_dict(state)


def test_stream_is_endless_across_generator_chunks():
    """Index i is reasoning-gym's item i for the same seed, also past one chunk of CHUNK items."""
    reference = reasoning_gym.create_dataset("chain_sum", **DEFAULT_MAIN_TASK.config, seed=9, size=CHUNK + 10)
    for index in (0, CHUNK - 1, CHUNK, CHUNK + 7):
        ours, theirs = generate_entry(DEFAULT_MAIN_TASK, seed=9, index=index), reference[index]
        assert (ours["question"], ours["answer"]) == (theirs["question"], theirs["answer"])


def test_eval_set_larger_than_the_space_is_rejected():
    with pytest.raises(ValueError, match="only 200 distinct questions"):
        build_eval_set(ONE_DIGIT_PAIRS, size=201, max_draws_per_item=20)


def test_stream_reports_an_exhausted_space():
    everything = build_eval_set(ONE_DIGIT_PAIRS, size=200)
    stream = ReasoningGymStream(ONE_DIGIT_PAIRS, exclude=everything, max_consecutive_skips=300)
    with pytest.raises(RuntimeError, match="nearly exhausted"):
        next(stream)


def test_task_errors_name_the_problem():
    with pytest.raises(ValueError, match="'seed'"):
        ReasoningGymTask("chain_sum", {"seed": 3})
    with pytest.raises(KeyError, match="chain_summ"):
        generate_entry(ReasoningGymTask("chain_summ"), seed=0, index=0)
    with pytest.raises(TypeError, match="max_term"):
        generate_entry(ReasoningGymTask("chain_sum", {"max_term": 3}), seed=0, index=0)
    with pytest.raises(ValueError, match="invalid config"):
        generate_entry(ReasoningGymTask("chain_sum", {"min_terms": 3, "max_terms": 2}), seed=0, index=0)


def test_list_valued_options_from_omegaconf_reach_the_generator():
    from omegaconf import OmegaConf

    config = OmegaConf.create({"min_terms": 2, "max_terms": 2, "operators": ["*"]})
    task = ReasoningGymTask("basic_arithmetic", config)
    assert task.config["operators"] == ["*"]
    expressions = [generate_entry(task, seed=0, index=i)["metadata"]["expression"] for i in range(20)]
    assert all(" * " in e and " + " not in e and " / " not in e for e in expressions)
