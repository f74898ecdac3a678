"""Verifiable rewards: response text + Problem -> `RewardResult`, behind a registry.

Every verifier is a callable ``(response_text, problem) -> RewardResult``. Callers go through
`safe_score`, which turns a verifier exception into ``reward=0, error=...`` for that one sample:
one malformed answer or buggy user function must not kill a training step, yet the failure must
be counted (`summarize_rewards` reports ``verifier_errors``), not silently scored as "wrong".

Registered names: ``math`` (math-verify, LaTeX or numbers), ``gsm8k`` (number after ``####``),
``reasoning_gym`` (the task's own ``score_answer``). Any ``"package.module:function"`` string is
loaded as a user reward function.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any

from infinirl.registry import Registry
from infinirl.tasks.answers import (
    extract_after_marker,
    extract_first_number,
    extract_last_number,
    get_answer_extractor,
    parse_number,
)
from infinirl.tasks.problem import Problem


@dataclass
class RewardResult:
    """Outcome of scoring one response.

    ``reward`` is what the algorithm optimises; ``correct`` is the accuracy metric (they differ
    with partial credit or a format bonus); ``error`` is set when the verifier itself failed;
    ``metrics`` holds extra per-sample numbers that are averaged into logs.
    """

    reward: float
    correct: bool
    error: str | None = None
    metrics: dict[str, float] = field(default_factory=dict)


Verifier = Callable[[str, Problem], RewardResult]
VERIFIERS: Registry[Callable[..., Verifier]] = Registry("verifier")


# --- gsm8k -------------------------------------------------------------------------------------


@VERIFIERS.register("gsm8k")
@dataclass(frozen=True)
class Gsm8kVerifier:
    """Numeric equality of the model's final number with the ground truth.

    ``extraction="marker"`` reads the first number after the last ``####`` (what the default
    prompt asks for); ``"last_number"`` takes the last number anywhere; ``"auto"`` tries the
    marker, ``\\boxed{}``, ``Answer:``, then the last number. Commas, ``$`` and trailing ``.0``
    are normalised away by comparing exact values (``"1,000.00" == "1000"``).
    """

    extraction: str = "marker"

    def __post_init__(self) -> None:
        get_answer_extractor(self.extraction)  # fail at construction on a bad name

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        gold = parse_number(problem.answer)
        if gold is None:
            raise ValueError(
                f"gsm8k verifier: ground truth {problem.answer!r} of {problem.uid} is not a number"
            )
        segment = get_answer_extractor(self.extraction)(response)
        predicted = parse_number(extract_first_number(segment))
        correct = predicted is not None and predicted == gold
        found = float(predicted is not None)
        return RewardResult(float(correct), correct, metrics={"answer_found": found})


# --- math (math-verify) ------------------------------------------------------------------------


@lru_cache(maxsize=4096)
def _parse_gold(answer: str) -> tuple:
    """Parsed ground truth, cached: a GRPO group scores n responses against the same answer.

    The answer is wrapped in ``$...$`` because math-verify only reads intervals, tuples and sets
    as such inside math delimiters (bare ``[-2, 3)`` parses as the number 3).
    """
    return tuple(_math_parse(f"${answer}$") or _math_parse(answer))


def _math_parse(text: str) -> list:
    # parsing_timeout=None: math-verify's timeout uses signal.alarm, which raises "signal only
    # works in main thread" inside thread pools and Ray actor threads. We bound the work instead
    # by parsing only a short tail of the response (`MathVerifier.max_response_chars`).
    from math_verify import parse

    return parse(text, parsing_timeout=None)


def _math_equal(gold: Sequence, predicted: Sequence) -> bool:
    from math_verify import verify

    # timeout_seconds=None for the same reason as parsing_timeout above.
    return bool(verify(list(gold), list(predicted), timeout_seconds=None))


# math-verify logs a warning the first time timeouts are disabled; we disable them on purpose.
logging.getLogger("math_verify").setLevel(logging.ERROR)


@VERIFIERS.register("math")
@dataclass(frozen=True)
class MathVerifier:
    """Symbolic equivalence via math-verify: ``\\frac{1}{2}`` == ``0.5``, intervals, tuples, sets.

    The prediction is read from the last ``\\boxed{}`` if there is one, else from the text after
    the last ``####``, else from the response's final ``max_response_chars`` characters. Only the
    tail is parsed because timeouts are disabled (see `_math_parse`) and sympy on a long
    rambling response is the slow path; the final answer is at the end anyway.
    """

    max_response_chars: int = 1000

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        gold = _parse_gold(problem.answer)
        if not gold:
            raise ValueError(
                f"math verifier: cannot parse ground truth {problem.answer!r} of {problem.uid}"
            )
        predicted = _math_parse(self._answer_text(response))
        correct = bool(predicted) and _math_equal(gold, predicted)
        return RewardResult(float(correct), correct, metrics={"answer_found": float(bool(predicted))})

    def _answer_text(self, response: str) -> str:
        tail = response[-self.max_response_chars :]
        if "\\boxed" in tail or "\\fbox" in tail:
            return tail
        after_marker = extract_after_marker(tail)
        if after_marker is not None:
            if "$" in after_marker:
                return after_marker
            return "\\boxed{" + after_marker.rstrip(".") + "}"
        return tail


# --- reasoning-gym -----------------------------------------------------------------------------


@VERIFIERS.register("reasoning_gym")
@dataclass(frozen=True)
class ReasoningGymVerifier:
    """The generator's own ``score_answer(answer, entry)`` on the extracted answer.

    Extraction (default ``"auto"``: ``####``, ``\\boxed{}``, ``Answer:``, last number) yields a
    candidate string; when it is a whole phrase (``"#### The sum is 42."``) its last number is
    also tried, and the better score wins, so numeric tasks are not marked wrong for wording.

    reasoning-gym's scorers give substring partial credit (``"42"`` inside ``"42 apples"`` scores
    2/9). ``partial_credit=False`` (default) rounds that to 0: a binary reward keeps "reward" and
    "accuracy" the same quantity and removes an incentive to pad answers around the right digits.
    """

    extraction: str = "auto"
    partial_credit: bool = False

    def __post_init__(self) -> None:
        get_answer_extractor(self.extraction)

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        from infinirl.tasks.reasoning_gym_tasks import score_entry

        try:
            entry, task, config = (problem.metadata[k] for k in ("entry", "task", "config"))
        except KeyError as missing:
            raise ValueError(
                f"reasoning_gym verifier: problem {problem.uid} lacks metadata {missing}; build "
                "reasoning-gym problems with reasoning_gym_tasks "
                "(build_eval_set / ReasoningGymStream)."
            ) from None
        candidate = get_answer_extractor(self.extraction)(response)
        candidates = [candidate]
        if candidate is not None and extract_last_number(candidate) not in (None, candidate):
            candidates.append(extract_last_number(candidate))
        score = max(score_entry(c, entry, task, config) for c in candidates)
        correct = score >= 1.0
        reward = score if self.partial_credit else float(correct)
        return RewardResult(reward, correct, metrics={"answer_found": float(candidate is not None)})


# --- user functions by dotted path -------------------------------------------------------------


def load_function(dotted_path: str) -> Callable[..., Any]:
    """Import ``"package.module:function"``; errors name the part that is wrong."""
    module_name, sep, attribute = dotted_path.partition(":")
    if not sep or not module_name or not attribute:
        raise ValueError(
            f"reward function path {dotted_path!r} must look like 'package.module:function' "
            "(module path, a colon, then the function name)."
        )
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise ImportError(
            f"cannot import module {module_name!r} for reward function {dotted_path!r}: {error}. "
            "Is it installed or on PYTHONPATH?"
        ) from error
    target: Any = module
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise AttributeError(
                f"module {module_name!r} has no attribute {attribute!r} (reward function "
                f"{dotted_path!r}); check the name after the colon."
            )
        target = getattr(target, part)
    if not callable(target):
        raise TypeError(
            f"{dotted_path!r} is a {type(target).__name__}, not a callable reward function"
        )
    return target


@dataclass(frozen=True)
class FunctionVerifier:
    """Wraps a user ``fn(response_text, problem)`` returning a float, a dict or a RewardResult.

    A dict needs ``"reward"``; ``"correct"`` is optional (default: reward > 0) and every other
    numeric entry becomes a per-sample metric.
    """

    function: Callable[[str, Problem], Any]
    name: str = "user function"

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        return _to_reward_result(self.function(response, problem), self.name)


def _to_reward_result(value: Any, source: str) -> RewardResult:
    if isinstance(value, RewardResult):
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float, dict)):
        raise TypeError(
            f"reward function {source} returned {type(value).__name__}; return a float, a dict "
            "with a 'reward' key, or a RewardResult."
        )
    if isinstance(value, dict):
        if "reward" not in value:
            raise KeyError(
                f"reward function {source} returned a dict without 'reward'; keys: {sorted(value)}"
            )
        reward = float(value["reward"])
        correct = bool(value.get("correct", reward > 0))
        metrics = {k: float(v) for k, v in value.items() if k not in ("reward", "correct")}
        return RewardResult(reward, correct, metrics=metrics)
    return RewardResult(float(value), float(value) > 0)


# --- format bonus ------------------------------------------------------------------------------


@dataclass(frozen=True)
class WithFormatBonus:
    """Adds ``bonus`` to the reward when the response uses the instructed answer format.

    ``answer_format`` names an answer extractor (``"marker"`` for ``####``, ``"boxed"`` for
    ``\\boxed{}``); the format counts as followed when that extractor finds something. Off by
    default (see `build_verifier`): with a verifiable reward the format is learnt anyway once it
    is what gets answers read; a bonus only helps a model that almost never uses it.
    ``correct`` is untouched so accuracy stays comparable across runs with and without it.
    """

    inner: Verifier
    bonus: float
    answer_format: str = "marker"

    def __post_init__(self) -> None:
        get_answer_extractor(self.answer_format)

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        result = self.inner(response, problem)
        formatted = get_answer_extractor(self.answer_format)(response) is not None
        return replace(
            result,
            reward=result.reward + self.bonus * formatted,
            metrics={**result.metrics, "format_followed": float(formatted)},
        )


# --- construction, safe scoring, summaries -----------------------------------------------------


def build_verifier(
    name: str, format_bonus: float = 0.0, answer_format: str = "marker", **options: Any
) -> Verifier:
    """A verifier by registry name or ``"package.module:function"`` path, with its options.

    ``format_bonus > 0`` wraps it in `WithFormatBonus` checking ``answer_format``.
    """
    if ":" in name:
        if options:
            raise TypeError(f"reward function {name!r} takes no options, got {sorted(options)}")
        verifier: Verifier = FunctionVerifier(load_function(name), name)
    else:
        try:
            verifier = VERIFIERS.get(name)(**options)
        except TypeError as error:
            raise TypeError(f"bad options {options} for verifier {name!r}: {error}") from None
    return WithFormatBonus(verifier, format_bonus, answer_format) if format_bonus else verifier


@lru_cache(maxsize=128)
def get_verifier(name: str) -> Verifier:
    """Default-configured verifier for a `Problem.verifier` name (cached: built once per name)."""
    return build_verifier(name)


def safe_score(response: str, problem: Problem, verifier: Verifier | None = None) -> RewardResult:
    """Score one response, never raising: a failing verifier gives reward 0 and ``error`` set."""
    try:
        chosen = verifier if verifier is not None else get_verifier(problem.verifier)
        return chosen(response, problem)
    except Exception as error:  # noqa: BLE001 - isolating arbitrary verifier code is the point
        return RewardResult(0.0, False, error=f"{type(error).__name__}: {error}")


def score_responses(
    responses: Sequence[str], problems: Sequence[Problem], verifier: Verifier | None = None
) -> list[RewardResult]:
    """`safe_score` for aligned lists (one problem per response; repeat problems for n samples)."""
    if len(responses) != len(problems):
        raise ValueError(
            f"score_responses: {len(responses)} responses but {len(problems)} problems"
        )
    return [safe_score(r, p, verifier) for r, p in zip(responses, problems)]


def summarize_rewards(results: Iterable[RewardResult]) -> dict[str, float]:
    """Batch metrics: mean reward, accuracy, verifier error count, and the mean of each metric."""
    results = list(results)
    if not results:
        return {"reward_mean": 0.0, "accuracy": 0.0, "verifier_errors": 0.0}
    summary = {
        "reward_mean": sum(r.reward for r in results) / len(results),
        "accuracy": sum(r.correct for r in results) / len(results),
        "verifier_errors": float(sum(r.error is not None for r in results)),
    }
    for name in sorted({k for r in results for k in r.metrics}):
        values = [r.metrics[name] for r in results if name in r.metrics]
        summary[f"{name}_mean"] = sum(values) / len(values)
    return summary


def check_verifier(name: str) -> None:
    """Raise if ``name`` names no registered verifier and no importable ``package.module:function``
    (the driver calls it before any reward worker starts)."""
    if ":" in name:
        load_function(name)
    else:
        VERIFIERS.get(name)
