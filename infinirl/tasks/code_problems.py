"""Generated function-writing problems: small string, list and arithmetic functions with random
parameters, each with a reference solution, examples in its docstring and hidden unit tests.

A family (:data:`FUNCTION_FAMILIES`) turns a ``random.Random`` into a :class:`FunctionTask`: the
function's name, signature, one-line description, reference solution (source) and an input
sampler, all with the family's parameters filled in. :func:`generate_function_problem` draws a
family and a task from ``Random(f"{seed}/{index}")`` (string seeds hash the same in every process),
so problem ``index`` of ``seed`` is a pure function of the two. Expected outputs come from running
the reference solution, the one source of truth (it is the project's own code, so it runs in this
process; the model's code never does).

The names and descriptions are the project's own, distinct from HumanEval's (a test checks that
no function name or prompt coincides), so HumanEval stays held out from training.
"""

from __future__ import annotations

import random
import string
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from infinirl.registry import Registry

__all__ = ["FUNCTION_FAMILIES", "FunctionTask", "GeneratedFunction", "generate_function", "make_stub",
           "make_tests"]


@dataclass(kw_only=True, frozen=True)
class FunctionTask:
    """One function to write, parameters filled in."""

    name: str
    signature: str
    """Parameters and return annotation, e.g. ``(xs: list[int]) -> int``."""
    description: str
    solution_body: str
    """The reference body (indented by four spaces)."""
    sample: Callable[[random.Random], tuple]
    """One random argument tuple."""

    def solution(self) -> str:
        return f"def {self.name}{self.signature}:\n{self.solution_body}"


@dataclass(kw_only=True, frozen=True)
class GeneratedFunction:
    """A generated problem: the stub shown to the model, its visible and hidden tests, a solution."""

    family: str
    entry_point: str
    stub: str
    solution: str
    tests: str
    visible_tests: str


FUNCTION_FAMILIES: Registry[Callable[[random.Random], FunctionTask]] = Registry("function family")
LETTERS = string.ascii_lowercase


def _ints(rng: random.Random, low: int = -20, high: int = 20, max_len: int = 7) -> list[int]:
    return [rng.randint(low, high) for _ in range(rng.randint(0, max_len))]


def _word(rng: random.Random, alphabet: str = "abcdehlnorst", low: int = 1, high: int = 7) -> str:
    return "".join(rng.choice(alphabet) for _ in range(rng.randint(low, high)))


@FUNCTION_FAMILIES.register("add_constant")
def _add_constant(rng):
    k = rng.randint(2, 99)
    return FunctionTask(name="add_constant", signature="(x: int) -> int", description=f"Return x plus {k}.",
                        solution_body=f"    return x + {k}\n", sample=lambda r: (r.randint(-100, 100),))


@FUNCTION_FAMILIES.register("scale_and_shift")
def _scale_and_shift(rng):
    a, b = rng.randint(2, 12), rng.randint(-30, 30)
    return FunctionTask(name="scale_and_shift", signature="(x: int) -> int",
                        description=f"Return x multiplied by {a}, plus {b}.",
                        solution_body=f"    return x * {a} + {b}\n", sample=lambda r: (r.randint(-50, 50),))


@FUNCTION_FAMILIES.register("count_char")
def _count_char(rng):
    c = rng.choice("aeinorst")
    return FunctionTask(name="count_char", signature="(s: str) -> int",
                        description=f"Return how many times the letter '{c}' occurs in s.",
                        solution_body=f"    return s.count({c!r})\n", sample=lambda r: (_word(r, "aeinorst", 0, 9),))


@FUNCTION_FAMILIES.register("repeat_join")
def _repeat_join(rng):
    k, sep = rng.randint(2, 5), rng.choice(["-", ",", "+", " ", "/"])
    return FunctionTask(name="repeat_join", signature="(s: str) -> str",
                        description=f"Return s repeated {k} times, with '{sep}' between the copies.",
                        solution_body=f"    return {sep!r}.join([s] * {k})\n", sample=lambda r: (_word(r),))


@FUNCTION_FAMILIES.register("keep_greater")
def _keep_greater(rng):
    k = rng.randint(-5, 10)
    return FunctionTask(name="keep_greater", signature="(xs: list[int]) -> list[int]",
                        description=f"Return the elements of xs that are greater than {k}, in their order.",
                        solution_body=f"    return [x for x in xs if x > {k}]\n", sample=lambda r: (_ints(r),))


@FUNCTION_FAMILIES.register("sum_divisible")
def _sum_divisible(rng):
    k = rng.randint(2, 7)
    return FunctionTask(name="sum_divisible", signature="(xs: list[int]) -> int",
                        description=f"Return the sum of the elements of xs that are divisible by {k}.",
                        solution_body=f"    return sum(x for x in xs if x % {k} == 0)\n",
                        sample=lambda r: (_ints(r, 0, 40),))


@FUNCTION_FAMILIES.register("clamp_value")
def _clamp_value(rng):
    low = rng.randint(-20, 10)
    high = low + rng.randint(1, 30)
    return FunctionTask(name="clamp_value", signature="(x: int) -> int",
                        description=f"Return {low} if x is below {low}, {high} if x is above {high}, else x.",
                        solution_body=f"    return max({low}, min({high}, x))\n",
                        sample=lambda r: (r.randint(low - 20, high + 20),))


@FUNCTION_FAMILIES.register("reverse_words")
def _reverse_words(rng):
    sep = rng.choice([" ", "-", ",", "_"])
    return FunctionTask(name="reverse_words", signature="(s: str) -> str",
                        description=f"Return the words of s (separated by single spaces) in reverse order, "
                                    f"joined by '{sep}'.",
                        solution_body=f"    return {sep!r}.join(reversed(s.split(' ')))\n",
                        sample=lambda r: (" ".join(_word(r) for _ in range(r.randint(1, 4))),))


@FUNCTION_FAMILIES.register("power_sum")
def _power_sum(rng):
    k = rng.randint(2, 4)
    return FunctionTask(name="power_sum", signature="(xs: list[int]) -> int",
                        description=f"Return the sum of the elements of xs, each raised to the power {k}.",
                        solution_body=f"    return sum(x ** {k} for x in xs)\n",
                        sample=lambda r: (_ints(r, -6, 6, 5),))


@FUNCTION_FAMILIES.register("replace_letter")
def _replace_letter(rng):
    a, b = rng.sample("aeinorst", 2)
    return FunctionTask(name="replace_letter", signature="(s: str) -> str",
                        description=f"Return s with every '{a}' replaced by '{b}'.",
                        solution_body=f"    return s.replace({a!r}, {b!r})\n",
                        sample=lambda r: (_word(r, "aeinorst", 0, 9),))


@FUNCTION_FAMILIES.register("every_kth")
def _every_kth(rng):
    k = rng.randint(2, 4)
    return FunctionTask(name="every_kth", signature="(xs: list[int]) -> list[int]",
                        description=f"Return every {k}th element of xs, starting with the first "
                                    f"(xs[0], xs[{k}], xs[{2 * k}], ...).",
                        solution_body=f"    return xs[::{k}]\n", sample=lambda r: (_ints(r, 0, 50, 10),))


@FUNCTION_FAMILIES.register("count_prefix")
def _count_prefix(rng):
    c = rng.choice("abcdehlnorst")
    return FunctionTask(name="count_prefix", signature="(words: list[str]) -> int",
                        description=f"Return how many strings in words start with the letter '{c}'.",
                        solution_body=f"    return sum(1 for w in words if w.startswith({c!r}))\n",
                        sample=lambda r: ([_word(r) for _ in range(r.randint(0, 5))],))


@FUNCTION_FAMILIES.register("digit_sum_times")
def _digit_sum_times(rng):
    k = rng.randint(2, 9)
    return FunctionTask(name="digit_sum_times", signature="(n: int) -> int",
                        description=f"Return the sum of the decimal digits of the non-negative integer n, "
                                    f"multiplied by {k}.",
                        solution_body=f"    return sum(int(d) for d in str(n)) * {k}\n",
                        sample=lambda r: (r.randint(0, 99999),))


@FUNCTION_FAMILIES.register("divisible_label")
def _divisible_label(rng):
    a, b = rng.sample([2, 3, 4, 5, 7], 2)
    first, second = rng.sample(["Ping", "Pong", "Tick", "Tock", "Zip", "Zap"], 2)
    return FunctionTask(name="divisible_label", signature="(n: int) -> str",
                        description=f"Return '{first}{second}' if n is divisible by both {a} and {b}, "
                                    f"'{first}' if only by {a}, '{second}' if only by {b}, else str(n).",
                        solution_body=(f"    if n % {a} == 0 and n % {b} == 0:\n        return {first + second!r}\n"
                                       f"    if n % {a} == 0:\n        return {first!r}\n"
                                       f"    if n % {b} == 0:\n        return {second!r}\n    return str(n)\n"),
                        sample=lambda r: (r.randint(1, 60),))


@FUNCTION_FAMILIES.register("rotate_letters")
def _rotate_letters(rng):
    k = rng.randint(1, 25)
    return FunctionTask(name="rotate_letters", signature="(s: str) -> str",
                        description=f"Move every lowercase letter of s {k} places forward in the alphabet, "
                                    f"wrapping around from 'z' to 'a'; keep other characters.",
                        solution_body=(f"    return ''.join(chr((ord(c) - 97 + {k}) % 26 + 97) if 'a' <= c <= 'z' "
                                       f"else c for c in s)\n"),
                        sample=lambda r: (_word(r, LETTERS + " !", 0, 9),))


@FUNCTION_FAMILIES.register("running_total")
def _running_total(rng):
    start = rng.randint(-10, 10)
    return FunctionTask(name="running_total", signature="(xs: list[int]) -> list[int]",
                        description=f"Return the list whose i-th element is {start} plus the sum of xs[0] "
                                    f"to xs[i].",
                        solution_body=(f"    out, total = [], {start}\n    for x in xs:\n        total += x\n"
                                       f"        out.append(total)\n    return out\n"),
                        sample=lambda r: (_ints(r),))


def _call(name: str, args: tuple) -> str:
    return f"{name}({', '.join(repr(a) for a in args)})"


def make_stub(task: FunctionTask, examples: Sequence[tuple[tuple, Any]]) -> str:
    """The signature and a docstring with the description and doctest examples."""
    lines = [f"def {task.name}{task.signature}:", f'    """{task.description}']
    for args, expected in examples:
        lines += [f"    >>> {_call(task.name, args)}", f"    {expected!r}"]
    return "\n".join(lines + ['    """', ""])


def make_tests(cases: Sequence[tuple[tuple, Any]], call: str = "candidate") -> str:
    """``check(candidate)`` asserting each ``<call>(*args) == expected`` (``call``: ``candidate``, or
    the function's own name, which reads better in the feedback a model gets)."""
    lines = ["def check(candidate):"]
    lines += [f"    assert {_call(call, args)} == {expected!r}" for args, expected in cases]
    return "\n".join(lines) + "\n"


def generate_function(rng: random.Random, families: Sequence[str] | None = None, num_examples: int = 2,
                      num_tests: int = 8) -> GeneratedFunction:
    """A problem from a family drawn with ``rng`` (of ``families``, default all): ``num_examples``
    distinct doctest examples (the visible tests) and up to ``num_tests`` further distinct cases."""
    names = list(families) if families else FUNCTION_FAMILIES.names()
    family = rng.choice(sorted(names))
    task = FUNCTION_FAMILIES.get(family)(rng)
    namespace: dict[str, Any] = {}
    exec(task.solution(), namespace)  # noqa: S102 - the project's own reference code
    reference = namespace[task.name]
    cases: dict[str, tuple[tuple, Any]] = {}
    for _ in range((num_examples + num_tests) * 10):
        if len(cases) == num_examples + num_tests:
            break
        args = task.sample(rng)
        cases.setdefault(repr(args), (args, reference(*args)))
    ordered = list(cases.values())
    examples, hidden = ordered[:num_examples], ordered[num_examples:]
    return GeneratedFunction(family=family, entry_point=task.name, stub=make_stub(task, examples),
                             solution=task.solution(), tests=make_tests(examples + hidden),
                             visible_tests=make_tests(examples, task.name) if examples else "")
