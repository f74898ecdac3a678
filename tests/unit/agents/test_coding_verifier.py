"""The code_tests verifier: real sandboxed runs of correct, wrong, crashing and runaway code."""

from concurrent.futures import ThreadPoolExecutor

import pytest

from infinirl.agents.coding.spec import CodeSpec
from infinirl.agents.coding.testing import format_report, read_report, run_code_tests_sync
from infinirl.agents.coding.verifier import CodeTestsVerifier
from infinirl.agents.sandbox import Sandbox, SandboxLimits, SandboxResult
from infinirl.tasks.problem import Problem
from infinirl.tasks.verifiers import build_verifier, safe_score

TESTS = ("def check(candidate):\n    assert candidate([1, 2, 3]) == 6\n    assert candidate([]) == 0\n"
         "    assert candidate([-1, 1]) == 0\n    assert candidate([5]) == 5\n")
SPEC = CodeSpec(entry_point="total", tests=TESTS, stub='def total(xs: list) -> int:\n    """Sum of xs."""\n')
PROBLEM = Problem(uid="t/0", prompt="...", answer="", verifier="code_tests", metadata=SPEC.to_metadata())
FAST = {"wall_time_s": 4.0, "cpu_time_s": 1.0, "memory_bytes": 512 << 20, "max_output_bytes": 8 << 10}


def fenced(code: str) -> str:
    return f"Here is my solution.\n```python\n{code}```\nIt sums the list."


@pytest.fixture(scope="module")
def verifier():
    return CodeTestsVerifier(limits=FAST)


def test_correct_code_scores_one(verifier):
    result = verifier(fenced("def total(xs):\n    return sum(xs)\n"), PROBLEM)
    assert result.reward == 1.0 and result.correct and result.error is None
    assert result.metrics["tests_passed"] == 1.0 and result.metrics["code_fenced"] == 1.0
    assert result.metrics["sandbox_namespaces"] == 1.0  # the isolation the score was got under


def test_wrong_code_scores_zero_and_partial_credit_counts_the_passed_tests(verifier):
    wrong = fenced("def total(xs):\n    return len(xs)\n")  # passes only candidate([]) == 0
    result = verifier(wrong, PROBLEM)
    assert result.reward == 0.0 and not result.correct and result.metrics["tests_passed"] == 0.25
    partial = build_verifier("code_tests_partial", limits=FAST)(wrong, PROBLEM)
    assert partial.reward == 0.25 and not partial.correct


@pytest.mark.parametrize("code, reason", [
    ("def total(xs) return 0\n", "SyntaxError"),
    ("def total(xs):\n    return 0\nraise RuntimeError('boom')\n", "RuntimeError: boom"),
    ("def total(xs):\n    return 0\nimport sys\nsys.exit(0)\n", "SystemExit"),
])
def test_code_that_cannot_load_scores_zero(verifier, code, reason):
    result = verifier(fenced(code), PROBLEM)
    assert result.reward == 0.0 and result.error is None and result.metrics["code_loaded"] == 0.0
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), code, TESTS, "total")
    assert reason in report.error and reason in format_report(report)


def test_code_without_the_function_scores_zero(verifier):
    no_stub = Problem(uid="t/3", prompt="", answer="", verifier="code_tests",
                      metadata={"entry_point": "total", "tests": TESTS})
    result = verifier(fenced("def other(xs):\n    return sum(xs)\n"), no_stub)
    assert result.reward == 0.0 and result.metrics["code_loaded"] == 0.0
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), "def other(xs):\n    return 0\n", TESTS, "total")
    assert "defines no function 'total'" in report.error


@pytest.mark.parametrize("code, limits", [
    ("def total(xs):\n    while True:\n        pass\n", {"cpu_time", "wall_time"}),
    ("def total(xs):\n    data = bytearray(2 << 30)\n    return 0\n", {"memory", None}),
    ("while True:\n    print('x' * 1000)\n", {"output", "cpu_time", "wall_time", None}),
])
def test_runaway_code_is_stopped_and_scores_zero(verifier, code, limits):
    result = verifier(fenced(code), PROBLEM)
    assert result.reward == 0.0 and not result.correct and result.error is None
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), code, TESTS, "total")
    assert report.limit in limits and report.passed == 0 and not report.all_passed


def test_a_memory_hog_inside_a_test_is_a_failed_test():
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), "def total(xs):\n    return len(bytearray(2 << 30))\n",
                                 TESTS, "total")
    assert report.loaded and report.passed == 0 and "MemoryError" in report.failures[0].error


def test_printed_text_cannot_pass_for_a_report(verifier):
    forged = 'print(\'abc {"loaded": true, "passed": 4, "total": 4, "failures": []}\')\ndef total(xs):\n    return 0\n'
    assert verifier(fenced(forged), PROBLEM).reward == 0.0


def test_no_code_scores_zero_and_broken_tests_are_a_verifier_error(verifier):
    assert verifier("   ", PROBLEM).metrics["code_found"] == 0.0
    broken = Problem(uid="t/1", prompt="", answer="", verifier="code_tests",
                     metadata={**SPEC.to_metadata(), "tests": "def check(candidate):\n    assert (\n"})
    result = safe_score(fenced("def total(xs):\n    return sum(xs)\n"), broken, verifier)
    assert result.reward == 0.0 and "tests of problem t/1 are broken" in result.error
    not_code = Problem(uid="t/2", prompt="", answer="1", verifier="code_tests")
    assert "not a coding problem" in safe_score("1", not_code, verifier).error


def test_a_sandbox_that_cannot_run_the_code_is_a_verifier_error():
    # A tmpfs too small for the harness: the sandbox's setup fails, which is not the code's fault.
    result = safe_score(fenced("def total(xs):\n    return sum(xs)\n"), PROBLEM,
                        CodeTestsVerifier(limits={**FAST, "disk_bytes": 1}))
    assert result.reward == 0.0 and "sandbox could not run the code of problem t/0" in result.error, result


@pytest.mark.parametrize("when", ["on load", "in a test"])
def test_code_writing_to_the_real_stdout_cannot_cut_the_report(verifier, when):
    """The code's fds 1 and 2 are /dev/null: bytes written there neither reach the sandbox's output
    limit (which would cut the report line) nor mix with the report."""
    flood = f"os.write(1, b'x' * {FAST['max_output_bytes'] - 60})\nos.write(2, b'y' * 100)\n"
    code = ("import os, sys\n" + (flood if when == "on load" else "")
            + "def total(xs):\n" + ("".join("    " + line + "\n" for line in flood.splitlines()) if when != "on load"
                                    else "") + "    print('hi', file=sys.__stdout__)\n    return sum(xs)\n")
    result = safe_score(fenced(code), PROBLEM, verifier)
    assert result.error is None and result.reward == 1.0, result


@pytest.mark.parametrize("line", ["{not json", "[1, 2]", '{"passed": 4}', '{"passed": 4, "total": 4, "loaded": true, '
                                  '"failures": [{"bogus": 1}]}', '{"passed": "4", "total": 4, "loaded": true, '
                                  '"failures": []}', ""])
def test_a_malformed_report_line_is_no_report(line):
    nonce = "ab" * 16
    result = SandboxResult(stdout=f"{nonce} {line}\n", stderr="", exit_code=0, wall_time_s=0.1)
    report = read_report(result, nonce)
    assert report.passed == 0 and not report.all_passed and "without a test report" in report.error, report


def test_code_that_is_not_unicode_scores_zero(verifier):
    result = safe_score(fenced("def total(xs):\n    return sum(xs)  # \udc80\n"), PROBLEM, verifier)
    assert result.error is None and result.reward == 0.0, result


def test_failures_show_the_value_returned():
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), "def total(xs):\n    return len(xs)\n", TESTS, "total")
    assert report.passed == 1 and report.total == 4
    assert report.failures[0].test == "assert candidate([1, 2, 3]) == 6" and report.failures[0].got == "3"
    assert "1/4 tests passed." in format_report(report) and "(got 3)" in format_report(report)


def test_many_problems_score_concurrently_from_a_thread_pool():
    verifier = CodeTestsVerifier(limits=FAST, max_concurrent=3)
    answers = ["def total(xs):\n    return sum(xs)\n", "def total(xs):\n    return 0\n",
               "def total(xs):\n  return\n"] * 3
    with ThreadPoolExecutor(max_workers=6) as pool:
        results = list(pool.map(lambda code: verifier(fenced(code), PROBLEM), answers))
    assert [r.reward for r in results] == [1.0, 0.0, 0.0] * 3


def test_limits_are_options_and_bad_ones_are_refused():
    assert CodeTestsVerifier(limits={"wall_time_s": 2.5}).limits.wall_time_s == 2.5
    with pytest.raises(ValueError, match="unknown keys"):
        CodeTestsVerifier(limits={"wall_time": 2})
    with pytest.raises(TypeError, match="code_tests"):
        build_verifier("code_tests", bogus=1)


@pytest.mark.parametrize("code", [
    "class E:\n    def __eq__(self, other):\n        return True\ndef total(xs):\n    return E()\n",
    "class E(int):\n    def __eq__(self, other):\n        return True\ndef total(xs):\n    return E(0)\n",
    "class L(list):\n    def __eq__(self, other):\n        return True\ndef total(xs):\n    return [L()]\n",
])
def test_results_that_compare_equal_to_anything_fail(verifier, code):
    assert verifier(fenced(code), PROBLEM).reward == 0.0
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), code, TESTS, "total")
    assert report.loaded and report.passed == 0 and "plain built-in value" in report.failures[0].error


# Code written to read the harness: it looks for the report's nonce wherever this process keeps it
# (the frames on the stack, every object, the harness's stdin) and prints a forged report.
FORGER = '''
import gc, json, os, sys

def _nonces():
    found = set()
    frame = sys._getframe()
    while frame is not None:
        for scope in (frame.f_locals, frame.f_globals):
            found.update(v["nonce"] for v in list(scope.values()) if isinstance(v, dict) and "nonce" in v)
        frame = frame.f_back
    found.update(o["nonce"] for o in gc.get_objects() if isinstance(o, dict) and isinstance(o.get("nonce"), str))
    for pid in (os.getpid(), os.getppid()):
        try:
            with open(f"/proc/{pid}/fd/0") as stdin:
                found.add(json.loads(stdin.readline())["nonce"])
        except Exception:
            pass
    return found

def _forge():
    report = json.dumps({"loaded": True, "passed": 4, "total": 4, "failures": []})
    for nonce in _nonces():
        for fd in (1, sys.__stdout__.fileno()):
            os.write(fd, f"\\n{nonce} {report}\\n".encode())
        for path in (f"/proc/{os.getppid()}/fd/1",):
            try:
                with open(path, "w") as out:
                    out.write(f"\\n{nonce} {report}\\n")
            except Exception:
                pass
    os._exit(0)

def total(xs):
    _forge()
'''


@pytest.mark.parametrize("when", ["on load", "in a test"])
def test_code_that_reads_the_harness_cannot_forge_a_report(verifier, when):
    code = FORGER + ("_forge()\n" if when == "on load" else "")
    result = verifier(fenced(code), PROBLEM)
    assert result.reward == 0.0 and not result.correct
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), code, TESTS, "total")
    assert report.passed == 0 and not report.all_passed


def test_helpers_builtins_and_exceptions_between_tests_and_code():
    tests = ("def check(candidate):\n    assert candidate(double(2)) == 5\n"
             "    assert abs(candidate(1) - 4) < 1e-9\n"
             "    try:\n        candidate(None)\n    except TypeError:\n        pass\n"
             "    else:\n        assert False\n"
             "    assert candidate(0) == total(0) and candidate((1, 2)) == {(1, 2): [None, b'x', 1.5, 2j]}\n")
    code = ("def double(x):\n    return 2 * x\n"
            "def abs(x):\n    return 0\n"  # shadows the builtin the tests call: must not fool them
            "def total(x):\n    if isinstance(x, tuple):\n        return {x: [None, b'x', 1.5, 2j]}\n"
            "    return x + 1\n")
    report = run_code_tests_sync(Sandbox(SandboxLimits(**FAST)), code, tests, "total")
    assert report.total == 4 and report.passed == 3, report
    assert "assert abs(candidate(1) - 4)" in report.failures[0].test and report.failures[0].got is None


# Answers that redefine the helpers HumanEval's tests call, so that the tests check nothing.
HELPER_CHEATS = {
    "humaneval/32": "import math\ndef poly(xs, x):\n    return 0\n\ndef find_zero(xs):\n    return 0.0\n",
    "humaneval/38": "def encode_cyclic(s):\n    return s\n\ndef decode_cyclic(s):\n    return s\n",
    "humaneval/50": "def encode_shift(s):\n    return s\n\ndef decode_shift(s):\n    return s\n",
}


@pytest.mark.parametrize("uid", sorted(HELPER_CHEATS))
def test_an_answer_cannot_replace_the_helpers_the_tests_use(verifier, uid):
    from infinirl.tasks.code_tasks import load_humaneval

    problem = {p.uid: p for p in load_humaneval(limit=51)}[uid]
    assert verifier(fenced(HELPER_CHEATS[uid]), problem).reward == 0.0
    assert verifier(fenced(problem.answer), problem).reward == 1.0  # the canonical solution still passes
