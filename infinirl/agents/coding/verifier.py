"""The ``code_tests`` verifier: run the model's code against the problem's unit tests in the sandbox.

The code is read from the model's text by :func:`~infinirl.agents.coding.extract.extract_code`
(the last ``python`` fenced block defining the problem's function, else the whole text; a body is
completed with the problem's stub), then :func:`~infinirl.agents.coding.testing.run_code_tests`
runs ``check(candidate)`` of ``problem.metadata["tests"]`` in a :class:`~infinirl.agents.Sandbox`.
Reward 1 when every test passes (``code_tests``), or the fraction passed (``code_tests_partial``);
``correct`` is always "every test passed". Bad code of any kind (no code, a syntax error, an
exception, an endless loop, a memory hog, a flood of output) scores 0 with the reason in the
metrics; only a problem whose own tests are broken, or a sandbox that could not run the code at all,
raises (counted as a verifier error). The sandbox needs namespaces unless ``limits`` names
``isolation: process`` (a verifier refuses to be built otherwise); metric ``sandbox_namespaces``
says which isolation a score was got under.

The reward worker calls verifiers from a thread pool: each call runs its own event loop, and a
process-wide semaphore bounds how many sandboxes run at once (``max_concurrent``).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import fields
from functools import partial
from typing import Any

from infinirl.agents.coding.extract import extract_code
from infinirl.agents.coding.spec import CodeSpec
from infinirl.agents.coding.testing import CodeTestReport, run_code_tests_sync
from infinirl.agents.sandbox import Sandbox, SandboxLimits
from infinirl.tasks.problem import Problem
from infinirl.tasks.verifiers import VERIFIERS, RewardResult

__all__ = ["DEFAULT_TEST_LIMITS", "CodeTestsVerifier", "make_limits"]

# Unit tests of small functions finish in well under a second; an endless loop should cost little.
DEFAULT_TEST_LIMITS = SandboxLimits(wall_time_s=10.0, cpu_time_s=4.0, memory_bytes=1 << 30,
                                    max_output_bytes=64 << 10, max_processes=16)
_SLOTS: dict[int, threading.BoundedSemaphore] = {}
_SLOTS_LOCK = threading.Lock()


def make_limits(limits: SandboxLimits | Mapping[str, Any] | None, default: SandboxLimits) -> SandboxLimits:
    """``limits`` as SandboxLimits: None gives ``default``, a mapping overrides fields of it."""
    if limits is None:
        return default
    if isinstance(limits, SandboxLimits):
        return limits
    known = {f.name for f in fields(SandboxLimits)}
    unknown = sorted(set(limits) - known)
    if unknown:
        raise ValueError(f"limits: unknown keys {unknown}; SandboxLimits has {sorted(known)}")
    return SandboxLimits(**{**{name: getattr(default, name) for name in known}, **dict(limits)})


def _slots(count: int) -> threading.BoundedSemaphore:
    with _SLOTS_LOCK:
        return _SLOTS.setdefault(count, threading.BoundedSemaphore(count))


class CodeTestsVerifier:
    """``limits``: SandboxLimits or a mapping of its fields (defaults: :data:`DEFAULT_TEST_LIMITS`);
    ``max_concurrent``: sandboxes running at once in this process; ``python``: the interpreter
    the code runs with (default: this one)."""

    def __init__(self, *, partial_credit: bool = False, limits: SandboxLimits | Mapping[str, Any] | None = None,
                 max_concurrent: int = 4, python: str | None = None, max_failures: int = 3):
        if max_concurrent < 1:
            raise ValueError(f"max_concurrent={max_concurrent}: must be >= 1")
        self.partial_credit = partial_credit
        self.limits = make_limits(limits, DEFAULT_TEST_LIMITS)
        self.sandbox = Sandbox(self.limits, python=python)
        self.slots = _slots(max_concurrent)
        self.max_failures = max_failures

    def test(self, code: str, spec: CodeSpec) -> CodeTestReport:
        """Run ``spec.tests`` against ``code`` (bounded by the process-wide concurrency)."""
        with self.slots:
            return run_code_tests_sync(self.sandbox, code, spec.tests, spec.entry_point, stub=spec.stub,
                                       max_failures=self.max_failures)

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        spec = CodeSpec.from_metadata(problem.metadata, problem.uid)
        extracted = extract_code(response, spec.entry_point, spec.stub)
        if extracted is None:
            return RewardResult(0.0, False, metrics={"code_found": 0.0, "code_loaded": 0.0, "tests_passed": 0.0,
                                                     "code_limit_hit": 0.0})
        report = self.test(extracted.code, spec)
        if report.harness_error:
            raise ValueError(f"the tests of problem {problem.uid} are broken: {report.harness_error}")
        if report.sandbox is not None and report.sandbox.error:  # nothing ran: not the code's fault
            raise RuntimeError(f"the sandbox could not run the code of problem {problem.uid}: {report.sandbox.error}")
        correct = report.all_passed
        reward = report.fraction if self.partial_credit else float(correct)
        return RewardResult(reward, correct, metrics={
            "code_found": 1.0, "code_fenced": float(extracted.fenced), "code_loaded": float(report.loaded),
            "tests_passed": report.fraction, "code_limit_hit": float(report.limit is not None),
            "sandbox_namespaces": float(report.sandbox is not None and report.sandbox.isolation == "namespaces")})


VERIFIERS.add("code_tests", CodeTestsVerifier)
VERIFIERS.add("code_tests_partial", partial(CodeTestsVerifier, partial_credit=True))
