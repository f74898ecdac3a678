"""The test harness that runs inside the sandbox as ``main.py`` (standard library only).

It reads one JSON line from stdin (``nonce``, ``entry_point``, ``max_failures``), executes
``solution.py`` (the model's code) with ``__name__ == "solution"`` so a ``__main__`` block does not
run, executes ``tests.py`` in the same namespace (tests may use helpers the problem's own code
defines), then runs the body of ``check(candidate)`` one top-level statement at a time with
``candidate`` bound to the solution's ``entry_point`` function. A statement counts as a test when it
contains an ``assert``; the report counts passed tests and describes the first failures (for an
``assert f(x) == y`` that failed, with the value ``f(x)`` returned).

What the code prints is captured (bounded) and returned in the report, which is one line on the real
stdout: ``<nonce> <json>``. The nonce is unknown to the code until it runs, so output the code
prints cannot pass for a report by accident; the code runs in this process, so code written to read
the harness could forge one (the sandbox limits what such code can reach, not what it reports).
"""

import ast
import io
import json
import sys
import traceback
import types

MAX_CAPTURED_CHARS = 2000
MAX_TEXT = 300
SOLUTION = "solution.py"
TESTS = "tests.py"


class CappedText(io.TextIOBase):
    """A text stream keeping the first ``limit`` characters written to it."""

    def __init__(self, limit):
        super().__init__()
        self.limit, self.parts, self.size = limit, [], 0

    def writable(self):
        return True

    def write(self, text):
        room = self.limit - self.size
        if room > 0:
            self.parts.append(text[:room])
            self.size += min(len(text), room)
        return len(text)

    def getvalue(self):
        return "".join(self.parts)


def cut(text, limit=MAX_TEXT):
    return text if len(text) <= limit else text[: limit - 3] + "..."


def describe(error):
    """``Type: message`` and the last line of the solution it came from."""
    text = "".join(traceback.format_exception_only(type(error), error)).strip()
    frames = [f for f in traceback.extract_tb(error.__traceback__) if f.filename == SOLUTION]
    if frames:
        text += f" (solution.py line {frames[-1].lineno})"
    return cut(text)


def check_statements(source):
    """``(parameter name, [(statement text, code, is_test)])`` of the tests' ``check`` function."""
    tree = ast.parse(source, TESTS)
    checks = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "check"]
    if not checks or not checks[-1].args.args:
        raise ValueError("tests.py defines no check(candidate) function")
    check = checks[-1]
    statements = []
    for statement in check.body:
        module = ast.Module(body=[statement], type_ignores=[])
        is_test = any(isinstance(node, ast.Assert) for node in ast.walk(statement))
        text = ast.get_source_segment(source, statement) or ast.dump(statement)
        statements.append((statement, text, compile(module, TESTS, "exec"), is_test))
    if not any(is_test for *_, is_test in statements):  # no asserts: every statement is a test
        statements = [(s, t, c, True) for s, t, c, _ in statements]
    return check.args.args[0].arg, statements


def returned_value(statement, namespace):
    """For a failed ``assert f(x) == y``: ``repr(f(x))``, else None."""
    test = getattr(statement, "test", None)
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return None
    try:
        value = eval(compile(ast.Expression(body=test.left), TESTS, "eval"), namespace)  # noqa: S307
    except BaseException:  # noqa: BLE001 - it already failed once; the message says how
        return None
    return cut(repr(value), 120)


def run_tests(namespace, entry_point, tests_source, max_failures, report):
    candidate = namespace.get(entry_point)
    if not callable(candidate):
        report["error"] = f"the code defines no function {entry_point!r}"
        return
    report["loaded"] = True
    exec(compile(tests_source, TESTS, "exec"), namespace)  # noqa: S102
    parameter, statements = check_statements(tests_source)
    namespace[parameter] = candidate
    report["total"] = sum(is_test for *_, is_test in statements)
    for statement, text, code, is_test in statements:
        try:
            exec(code, namespace)  # noqa: S102
        except BaseException as error:  # noqa: BLE001 - SystemExit from the candidate is a failure too
            if len(report["failures"]) < max_failures:
                failure = {"test": cut(text), "error": describe(error)}
                got = returned_value(statement, namespace) if isinstance(error, AssertionError) else None
                if got is not None:
                    failure["got"] = got
                report["failures"].append(failure)
        else:
            report["passed"] += is_test


def main():
    spec = json.loads(sys.stdin.readline())
    real_stdout = sys.stdout
    captured = CappedText(MAX_CAPTURED_CHARS)
    sys.stdout = sys.stderr = captured
    report = {"loaded": False, "passed": 0, "total": 0, "failures": []}
    module = types.ModuleType("solution")  # registered, so dataclasses and pickling find the code's module
    sys.modules["solution"] = module
    namespace = module.__dict__
    try:
        with open(SOLUTION, encoding="utf-8") as handle:
            solution = handle.read()
        with open(TESTS, encoding="utf-8") as handle:
            tests_source = handle.read()
        try:
            exec(compile(solution, SOLUTION, "exec"), namespace)  # noqa: S102
        except BaseException as error:  # noqa: BLE001 - whatever the code does is reported
            report["error"] = describe(error)
        else:
            try:
                run_tests(namespace, spec["entry_point"], tests_source, spec["max_failures"], report)
            except (SyntaxError, ValueError) as error:  # the problem's tests, not the code, are broken
                report["harness_error"] = f"{type(error).__name__}: {error}"
    finally:
        sys.stdout, sys.stderr = real_stdout, sys.__stderr__
        report["output"] = captured.getvalue()
        real_stdout.write(f"\n{spec['nonce']} {json.dumps(report)}\n")
        real_stdout.flush()


if __name__ == "__main__":
    main()
