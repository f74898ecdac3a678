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
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any

from infinirl.registry import Registry
from infinirl.tasks.answers import (
    extract_after_marker,
    extract_first_number,
    find_numbers,
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
    marker, ``<answer>`` tags, ``\\boxed{}``, ``Answer:``, then the last number. Commas, ``$`` and trailing ``.0``
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


@lru_cache(maxsize=4096)
def _gold_cheap_to_evaluate(answer: str) -> bool:
    return _cheap_to_evaluate(_parse_gold(answer))


def _math_parse(text: str) -> list:
    # parsing_timeout=None: math-verify's timeout uses signal.alarm, which raises "signal only
    # works in main thread" inside thread pools and Ray actor threads. We bound the work instead
    # by parsing only a short tail of the response (`MathVerifier.max_response_chars`).
    from math_verify import parse

    return parse(text, parsing_timeout=None)


def _math_equal(gold: Sequence, predicted: Sequence) -> bool:
    from math_verify import verify

    # timeout_seconds=None for the same reason as parsing_timeout above; `_cheap_to_evaluate`
    # bounds the work instead.
    return bool(verify(list(gold), list(predicted), timeout_seconds=None))


# Bounds on what math-verify is asked to evaluate. Parsing leaves expressions unevaluated, but
# comparing evaluates them, and ``10^{10^{10}}`` or ``99999999!`` would take forever (no timeout can
# interrupt sympy in a worker thread). Within these bounds a comparison takes about a second at most.
MAX_EXPRESSION_NODES = 2000
MAX_POWER_DIGITS = 10_000
"""A power of numbers may have at most this many digits (|exponent| * |log10 base|)."""
MAX_SYMBOLIC_EXPONENT = 1000
"""Largest |exponent| of a power of an expression with variables (``x^{1000}`` passes)."""
MAX_EXPANSION_TERMS = 500
"""Terms of a power of a sum once multiplied out: ``(x+1)^{300}`` and ``(x+y+1)^{30}`` pass; a tenth of
that when the sum holds functions (``(\\sin x + 1)^{49}`` passes)."""
MAX_FACTORIAL_ARGUMENT = 1000
"""Largest argument of a factorial, gamma function or binomial coefficient."""


def _cheap_to_evaluate(parsed: Sequence) -> bool:
    """Whether the sympy expressions of a math-verify parse are within the bounds above."""
    try:
        return _within_bounds(parsed)
    except RecursionError:  # nested deeper than sympy itself can walk
        return False


def _within_bounds(parsed: Sequence) -> bool:
    import sympy
    from sympy.functions.combinatorial.factorials import FallingFactorial, RisingFactorial

    growing = (sympy.factorial, sympy.factorial2, sympy.subfactorial, sympy.gamma, sympy.binomial,
               RisingFactorial, FallingFactorial)
    nodes: list = []
    for item in parsed:
        if isinstance(item, sympy.Basic):
            for node in sympy.preorder_traversal(item):
                nodes.append(node)
                if len(nodes) > MAX_EXPRESSION_NODES:
                    return False
    # Reversed preorder puts every node after its subexpressions, so an exponent or argument is
    # only evaluated once its own parts have passed.
    for node in reversed(nodes):
        if isinstance(node, sympy.Pow) and _power_too_costly(node.base, node.exp):
            return False
        if isinstance(node, sympy.exp) and _power_too_costly(sympy.E, node.args[0]):
            return False
        if isinstance(node, growing) and any(
                (size := _log10_magnitude(argument)) is not None and size > math.log10(MAX_FACTORIAL_ARGUMENT)
                for argument in node.args):
            return False
    return True


def _power_too_costly(base: Any, exponent: Any) -> bool:
    import sympy

    size = _log10_magnitude(exponent)
    if size is None:  # a symbolic exponent: nothing to evaluate
        return False
    if base.free_symbols:
        if size > math.log10(MAX_SYMBOLIC_EXPONENT):
            return True
        if not base.has(sympy.Add):
            return False
        # Terms with functions (sin x) are each simplified on their own: much slower.
        most = MAX_EXPANSION_TERMS // 10 if base.atoms(sympy.Function) else MAX_EXPANSION_TERMS
        degree, variables = _degree(base) * 10**size, len(base.free_symbols)
        return degree > most or math.comb(round(degree) + variables, variables) > most
    base_size = _log10_magnitude(base)
    if base_size is None or base_size in (0.0, -math.inf):  # 0, 1 and -1 to any power are cheap
        return False
    return size > 20 or 10**size * abs(base_size) > MAX_POWER_DIGITS


def _degree(expr: Any) -> float:
    """The total degree of ``expr`` as a polynomial in its variables (1 for anything else with
    variables in it)."""
    import sympy

    if not expr.free_symbols:
        return 0.0
    if isinstance(expr, sympy.Add):
        return max(_degree(term) for term in expr.args)
    if isinstance(expr, sympy.Mul):
        return sum(_degree(factor) for factor in expr.args)
    if isinstance(expr, sympy.Pow) and (size := _log10_magnitude(expr.exp)) is not None:
        return _degree(expr.base) * 10**size
    return 1.0


def _same_expression(gold: Sequence, predicted: Sequence) -> bool:
    """Structural equality of the parsed expressions, with nothing evaluated."""
    return any(not isinstance(g, str) and not isinstance(p, str) and g == p for g in gold for p in predicted)


def _log10_magnitude(expr: Any) -> float | None:
    """log10 |value| of an expression without variables (-inf for 0); None when it has variables
    or no numeric value. Evaluated at low precision: cheap once its parts passed the bounds."""
    import sympy

    if not isinstance(expr, sympy.Basic) or expr.free_symbols:
        return None
    try:
        magnitude = sympy.Abs(expr.evalf(15)).evalf(15)
        if not magnitude.is_Number or magnitude.is_infinite or magnitude is sympy.nan:
            return None
        return -math.inf if magnitude == 0 else float(sympy.log(magnitude, 10).evalf(15))
    except (TypeError, ValueError, ArithmeticError, AttributeError):
        return None


# math-verify logs a warning the first time timeouts are disabled; we disable them on purpose.
logging.getLogger("math_verify").setLevel(logging.ERROR)


@VERIFIERS.register("math")
@dataclass(frozen=True)
class MathVerifier:
    """Symbolic equivalence via math-verify: ``\\frac{1}{2}`` == ``0.5``, intervals, tuples, sets.

    The prediction is read from the last ``\\boxed{}`` if there is one, else from the text after
    the last ``####``, else from the response's final ``max_response_chars`` characters. Only the
    tail is parsed because timeouts are disabled (see `_math_parse`) and sympy on a long
    rambling response is the slow path; the final answer is at the end anyway. For the same reason
    an answer (or ground truth) beyond the bounds of `_cheap_to_evaluate` (``10^{10^{10}}``,
    ``99999999!``, ``(x+1)^{1000}``) is not evaluated: it is correct only when it is the ground truth's
    expression as parsed, so ``\\boxed{10^{10^{10}}}`` still matches a ground truth ``10^{10^{10}}``.
    """

    max_response_chars: int = 1000

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        gold = _parse_gold(problem.answer)
        if not gold:
            raise ValueError(
                f"math verifier: cannot parse ground truth {problem.answer!r} of {problem.uid}"
            )
        predicted = _math_parse(self._answer_text(response))
        if not predicted:
            correct = False
        elif _gold_cheap_to_evaluate(problem.answer) and _cheap_to_evaluate(predicted):
            correct = _math_equal(gold, predicted)
        else:  # too costly to evaluate: only the same expression, as written, is the same answer
            correct = _same_expression(gold, predicted)
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

    Extraction (default ``"auto"``: ``####``, ``<answer>``, ``\\boxed{}``, ``Answer:``, last number) yields a
    candidate string; when it is a whole phrase holding exactly one number (``"#### The sum is
    42."``) that number is also tried, and the better score wins, so numeric tasks are not marked
    wrong for wording (``"#### 6 or 5"`` holds two guesses: only the phrase is scored).

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
        numbers = find_numbers(candidate) if candidate is not None else []
        if len(numbers) == 1 and numbers[0] != candidate:  # more than one would be several guesses
            candidates.append(numbers[0])
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
    result = _as_reward_result(value, source)
    if not math.isfinite(result.reward):
        # A NaN would poison the batch's advantages and means; an error is counted and scored 0.
        raise ValueError(f"reward function {source} returned a reward of {result.reward}, not a finite number")
    return result


def _as_reward_result(value: Any, source: str) -> RewardResult:
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
    """Adds ``bonus`` to the reward when the response gives an answer in the instructed format.

    ``answer_format`` names an answer extractor (``"marker"`` for ``####``, ``"boxed"`` for
    ``\\boxed{}``, ``"tagged"`` for ``<answer>`` tags: the task's, ``task.answer_format``); the format
    counts as followed when that extractor finds something and the inner verifier found an answer
    (its ``answer_found`` metric, where it reports one): ``#### banana`` on a numeric task earns
    nothing. Off by
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
        formatted = (result.metrics.get("answer_found", 1.0) > 0
                     and get_answer_extractor(self.answer_format)(response) is not None)
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
