"""The write-run-fix environment (``rollout.agent.env: code_runner``).

The model writes its function in a ```` ```python ```` block; the turn is handed to the environment
when the block's closing fence is followed by a newline (the stop string ```` ```\\n ````). The
environment reads the code by the verifier's rule (:mod:`~infinirl.agents.coding.extract`), runs it
in the sandbox against the problem's visible tests (the examples its prompt shows; ``feedback:
all`` uses every test), and answers with what passed and what failed (with the value returned)
and what the code printed. When every test passes, the trajectory ends (``stop_when_passing``);
otherwise the model may fix the code in its next turn. The reward is the ``code_tests`` verifier's
on the last code the model wrote. A turn that ends without the stop string (EOS right after the
closing fence) is the answer, unless ``run_answers``: then its code runs as well while another turn
is left, so a policy cannot skip the feedback by ending its turn there; the observation then starts
after the end-of-turn text the model wrote (the template's leading ``<|im_end|>`` is not repeated).

Without a problem (``reset(None)``, or a problem without tests), the code runs as a program and
the observation is its output: stdout, stderr and how it ended.

A turn that ends on an opening fence without a language tag (```` ```\\n ```` opening a block) is
not code yet: the environment answers with nothing and the model continues the same turn's text.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any, Literal

from infinirl.agents.coding.extract import CODE_LANGUAGES, code_blocks, extract_code
from infinirl.agents.coding.spec import CodeSpec
from infinirl.agents.coding.testing import format_report, run_code_tests_sync
from infinirl.agents.coding.verifier import DEFAULT_TEST_LIMITS, make_limits
from infinirl.agents.loop import AGENT_ENVS, AgentEnv, AgentStep, drop_start, overlap, template_parts
from infinirl.agents.sandbox import Sandbox, SandboxLimits
from infinirl.agents.tools import summarize_run

__all__ = ["DEFAULT_OBSERVATION", "CodeRunnerEnv"]

Feedback = Literal["visible", "all", "run"]
DEFAULT_OBSERVATION = "\nResult:\n{feedback}\n"


@AGENT_ENVS.register("code_runner")
class CodeRunnerEnv(AgentEnv):
    """``feedback``: which tests a turn's code runs against (``visible``: the prompt's examples,
    falling back to running the code when a problem has none; ``all``: every test; ``run``: none,
    just run it). ``observation_template``: the text around the feedback, with ``{feedback}``
    (e.g. a chat template's user turn), kept whole when the feedback is cut to the loop's
    ``max_observation_tokens``. ``stop_strings``: where a turn is handed over. ``limits``:
    SandboxLimits or a mapping of its fields. ``run_answers``: run the code of turns that end without
    a stop string too (see the module docstring)."""

    def __init__(self, feedback: Feedback = "visible", observation_template: str = DEFAULT_OBSERVATION,
                 stop_strings: Sequence[str] = ("```\n",), stop_when_passing: bool = True,
                 limits: SandboxLimits | Mapping[str, Any] | None = None, max_feedback_chars: int = 1200,
                 max_failures: int = 2, python: str | None = None, run_answers: bool = False):
        if feedback not in ("visible", "all", "run"):
            raise ValueError(f"feedback={feedback!r}: use visible, all or run")
        if "{feedback}" not in observation_template:
            raise ValueError(f"observation_template={observation_template!r} has no {{feedback}} placeholder")
        if not stop_strings or any(not s for s in stop_strings):
            raise ValueError("stop_strings: give at least one non-empty string")
        if not isinstance(run_answers, bool):
            raise ValueError(f"run_answers={run_answers!r}: use true or false")
        if max_feedback_chars < 20:
            raise ValueError(f"max_feedback_chars={max_feedback_chars}: must be >= 20")
        self.feedback, self.template, self.stop_when_passing = feedback, observation_template, stop_when_passing
        self.stop_strings = tuple(stop_strings)
        self.step_answer_turns = run_answers
        self.sandbox = Sandbox(make_limits(limits, DEFAULT_TEST_LIMITS), python=python)
        self.max_feedback_chars, self.max_failures = max_feedback_chars, max_failures
        self.spec: CodeSpec | None = None

    def reset(self, problem: Any) -> None:
        self.spec = CodeSpec.of(problem)

    def step(self, turn: str) -> AgentStep:
        blocks = code_blocks(turn)
        if blocks and not blocks[-1][1].strip() and not blocks[-1][2]:  # stopped right after an opening fence
            return AgentStep(observation="", info={"open_fence": 1})
        if not any(language in CODE_LANGUAGES for language, _, _ in blocks):
            return AgentStep(done=True)  # no code in the turn: it is the answer
        spec = self.spec
        extracted = extract_code(turn, spec.entry_point if spec else None, spec.stub if spec else None)
        if extracted is None:
            return AgentStep(done=True)
        tests = self._tests(spec)
        start = time.perf_counter()
        if tests is None:
            result = self.sandbox.run_sync(extracted.code)
            passed, text = result.ok, summarize_run(result, self.max_feedback_chars)
            info = {"code_runs": 1, "code_ok": float(result.ok)}
        else:
            report = run_code_tests_sync(self.sandbox, extracted.code, tests, spec.entry_point, stub=spec.stub,
                                         max_failures=self.max_failures)
            passed, text = report.all_passed, format_report(report, self.max_feedback_chars)
            info = {"code_runs": 1, "code_ok": float(report.all_passed), "visible_tests_passed": report.fraction}
            result = report.sandbox
        info["sandbox_namespaces"] = float(result is not None and result.isolation == "namespaces")
        info["code_run_s"] = time.perf_counter() - start
        if passed and self.stop_when_passing:
            return AgentStep(done=True, info=info)
        # The template's text is kept whole when the feedback is cut to fit the budget: its end
        # hands the turn back to the model.
        parts = template_parts(self.template, "{feedback}", ((text, True),))
        if not any(stop in turn for stop in self.stop_strings):  # an answer turn (run_answers)
            info["answer_runs"] = 1
            parts = drop_start(parts, overlap(turn, "".join(piece for piece, _ in parts)))
        return AgentStep(parts=parts, info=info)

    def _tests(self, spec: CodeSpec | None) -> str | None:
        if spec is None or self.feedback == "run":
            return None
        if self.feedback == "all":
            return spec.tests
        return spec.visible_tests or None

