"""Run a program against a problem's tests in the sandbox and read the harness's report.

``await run_code_tests(sandbox, code, tests, entry_point)`` writes ``code`` as ``solution.py`` and
``tests`` (source defining ``check(candidate)``) as ``tests.py`` beside the harness
(:mod:`~infinirl.agents.coding.harness`), runs it with the sandbox's limits, and returns a
:class:`CodeTestReport`. It never raises for anything the code does: code that does not compile,
raises, loops forever, exhausts memory or floods its output is a report with ``passed == 0`` (or
the tests it passed before), ``error`` or ``limit`` saying what happened.
"""

from __future__ import annotations

import asyncio
import json
import secrets
from dataclasses import dataclass, field
from pathlib import Path

from infinirl.agents.coding.extract import stub_preamble
from infinirl.agents.sandbox import Sandbox, SandboxLimits, SandboxResult

__all__ = ["HARNESS_SOURCE", "CodeTestReport", "TestFailure", "format_report", "run_code_tests",
           "run_code_tests_sync"]

HARNESS_SOURCE = Path(__file__).with_name("harness.py").read_text(encoding="utf-8")


@dataclass(kw_only=True, frozen=True)
class TestFailure:
    test: str
    """The failing statement of ``check`` (cut to a few hundred characters)."""
    error: str
    """``Type: message`` of what it raised."""
    got: str | None = None
    """For a failed ``assert f(x) == y``: ``repr(f(x))``."""


@dataclass(kw_only=True, frozen=True)
class CodeTestReport:
    passed: int = 0
    total: int = 0
    loaded: bool = False
    """The code ran to its end and defined the function (the tests could start)."""
    error: str | None = None
    """Why the tests could not run: the code raised on load, defined no such function, or the run
    ended without a report (a limit, a crash)."""
    limit: str | None = None
    """The sandbox limit that ended the run (``wall_time``, ``cpu_time``, ``memory``, ``output``, ``processes``)."""
    failures: tuple[TestFailure, ...] = ()
    output: str = ""
    """What the code printed (the first couple of thousand characters)."""
    harness_error: str | None = None
    """The problem's tests themselves are broken (no ``check``, a syntax error): not the code's fault."""
    wall_time_s: float = 0.0
    sandbox: SandboxResult | None = field(default=None, repr=False, compare=False)

    @property
    def all_passed(self) -> bool:
        return self.loaded and self.total > 0 and self.passed == self.total and self.limit is None

    @property
    def fraction(self) -> float:
        return self.passed / self.total if self.total else 0.0


async def run_code_tests(sandbox: Sandbox, code: str, tests: str, entry_point: str, *, stub: str = "",
                         limits: SandboxLimits | None = None, max_failures: int = 3) -> CodeTestReport:
    """Run ``tests`` against ``entry_point`` of ``code`` in ``sandbox`` (see the module docstring).
    ``stub``: the problem's stub; what it declares before the function (helpers such as HumanEval's
    ``encode_shift``) is defined in the tests' own process, so the tests call the problem's helpers,
    never ones the code redefined."""
    nonce = secrets.token_hex(16)
    spec = json.dumps({"nonce": nonce, "entry_point": entry_point, "max_failures": max_failures,
                       "preamble": stub_preamble(stub, entry_point) if stub else ""})
    result = await sandbox.run(HARNESS_SOURCE, stdin=spec + "\n", files={"solution.py": code, "tests.py": tests},
                               limits=limits)
    return read_report(result, nonce)


def run_code_tests_sync(sandbox: Sandbox, code: str, tests: str, entry_point: str, **options) -> CodeTestReport:
    """:func:`run_code_tests` from synchronous code (not inside a running event loop)."""
    return asyncio.run(run_code_tests(sandbox, code, tests, entry_point, **options))


def parse_report(text: str) -> dict | None:
    """The harness's report from the JSON after the nonce, or None if it is not one (a line cut at
    the output limit, or malformed): a run without a report, never an exception."""
    try:
        report = json.loads(text)
    except ValueError:
        return None
    if not (isinstance(report, dict) and type(report.get("passed")) is int and type(report.get("total")) is int
            and type(report.get("loaded")) is bool and isinstance(report.get("failures"), list)):
        return None
    try:
        report["failures"] = tuple(TestFailure(**failure) for failure in report["failures"])
    except TypeError:  # not a mapping, or other fields
        return None
    text_fields = [report.get(key) for key in ("error", "harness_error", "output")]
    failure_fields = [value for failure in report["failures"] for value in (failure.test, failure.error, failure.got)]
    if not all(value is None or isinstance(value, str) for value in text_fields + failure_fields):
        return None
    return report


def read_report(result: SandboxResult, nonce: str) -> CodeTestReport:
    """The harness's report line in ``result.stdout``, or a report of why there is none."""
    limit = None if result.limit is None else str(result.limit)
    report = None
    for line in reversed(result.stdout.splitlines()):
        if line.startswith(nonce + " "):
            report = parse_report(line[len(nonce) + 1:])
            break
    if report is None:
        if result.error:
            error = f"sandbox error: {result.error}"
        elif limit:
            error = f"stopped: {limit} limit"
        else:
            tail = result.stderr.strip().splitlines()[-1:] or [f"exit code {result.exit_code}"]
            error = f"the run ended without a test report ({tail[0][:200]})"
        return CodeTestReport(error=error, limit=limit, wall_time_s=result.wall_time_s, sandbox=result)
    passed = report["passed"] if limit is None else 0  # a run a limit ended passes nothing
    return CodeTestReport(passed=passed, total=report["total"], loaded=report["loaded"], error=report.get("error"),
                          limit=limit, failures=report["failures"], output=report.get("output") or "",
                          harness_error=report.get("harness_error"), wall_time_s=result.wall_time_s, sandbox=result)


def format_report(report: CodeTestReport, max_chars: int = 1500) -> str:
    """The model's view of a test run: how many passed, the failures, and what the code printed."""
    if report.harness_error:
        lines = [f"The tests could not run: {report.harness_error}"]
    elif not report.loaded:
        lines = [f"The code did not run: {report.error}"]
    else:
        lines = [f"{report.passed}/{report.total} tests passed."]
        for failure in report.failures:
            got = f" (got {failure.got})" if failure.got is not None else ""
            lines.append(f"Failed: {failure.test}{got}: {failure.error}")
        if report.limit:
            lines.append(f"Stopped: {report.limit} limit.")
    if report.output.strip():
        lines.append("Printed:\n" + report.output.rstrip("\n"))
    text = "\n".join(lines)
    return text if len(text) <= max_chars else text[: max_chars - 15] + "\n[truncated]"
