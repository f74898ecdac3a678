"""Exact arithmetic on a model-written expression, without ``eval``.

The expression is parsed with :mod:`ast` and only numbers, ``+ - * / // % **``, unary signs,
parentheses and a few functions (abs, min, max, round) are evaluated, all as exact
:class:`fractions.Fraction` (``0.1 + 0.2`` is exactly ``0.3``). Every intermediate value is kept
below :data:`MAX_BITS` bits and a power is checked before it is computed, so ``10**10**10`` fails at
once with a clear message instead of hanging the caller.
"""

from __future__ import annotations

import ast
import math
import operator
from decimal import Decimal
from fractions import Fraction

__all__ = ["MAX_BITS", "MAX_EXPRESSION_CHARS", "CalculatorError", "evaluate", "format_number"]

MAX_EXPRESSION_CHARS = 1000
MAX_DEPTH = 100  # operators nested in one another: checked, not left to the interpreter's recursion limit
MAX_BITS = 9900  # about 3000 decimal digits: below Python's int-to-text limit (4300 digits)
APPROXIMATE_DIGITS = 20
MAX_DECIMAL_DIGITS = 4000  # a longer finite decimal is shown as p/q ≈ ... (Python prints at most 4300 digits)

BINARY = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: operator.truediv,
    ast.FloorDiv: operator.floordiv,
    ast.Mod: operator.mod,
}
UNARY = {ast.UAdd: operator.pos, ast.USub: operator.neg}


class CalculatorError(ValueError):
    """An expression the calculator refuses; the message is meant for the model to read."""


def shorten(text: str, limit: int = 80) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def size_bits(value: Fraction) -> int:
    return max(value.numerator.bit_length(), value.denominator.bit_length())


def checked(value: Fraction) -> Fraction:
    if size_bits(value) > MAX_BITS:
        raise CalculatorError(f"a value has more than {MAX_BITS} bits (about {int(MAX_BITS * 0.30103)} digits); "
                              "the calculator keeps numbers below that")
    return value


def power(base: Fraction, exponent: Fraction) -> Fraction:
    if exponent.denominator != 1:
        raise CalculatorError("powers take integer exponents only (no roots)")
    if base == 0 and exponent < 0:
        raise CalculatorError("division by zero (0 to a negative power)")
    if base in (0, 1):
        return base
    if base == -1:
        return Fraction(1 if exponent.numerator % 2 == 0 else -1)
    estimated = abs(exponent.numerator) * max(size_bits(base) - 1, 1)
    if estimated > MAX_BITS:
        raise CalculatorError(f"the power would have about {int(estimated * 0.30103)} digits; the calculator keeps "
                              f"numbers below {int(MAX_BITS * 0.30103)} digits")
    return checked(base ** exponent.numerator)


def to_int(value: Fraction, what: str) -> int:
    if value.denominator != 1:
        raise CalculatorError(f"{what} must be an integer, got {format_number(value)}")
    return value.numerator


def call_round(*args: Fraction) -> Fraction:
    if len(args) == 1:
        return Fraction(round(args[0]))
    if len(args) == 2:
        digits = to_int(args[1], "round()'s digits")
        if abs(digits) > 1000:
            raise CalculatorError("round()'s digits must be between -1000 and 1000")
        return Fraction(round(args[0], digits))
    raise CalculatorError("round() takes a number and optionally a number of digits")


def call_abs(*args: Fraction) -> Fraction:
    if len(args) != 1:
        raise CalculatorError("abs() takes exactly one number")
    return abs(args[0])


def call_min_max(function):
    def call(*args: Fraction) -> Fraction:
        if not args:
            raise CalculatorError(f"{function.__name__}() needs at least one number")
        return function(args)

    return call


FUNCTIONS = {"abs": call_abs, "min": call_min_max(min), "max": call_min_max(max), "round": call_round}


def literal(value: object) -> Fraction:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise CalculatorError(f"only numbers are allowed, got {value!r}")
    if isinstance(value, float):
        if not math.isfinite(value):
            raise CalculatorError(f"only finite numbers are allowed, got {value!r}")
        return checked(Fraction(Decimal(repr(value))))  # 0.1 is one tenth, not the nearest binary float
    return checked(Fraction(value))


def evaluate_node(node: ast.AST) -> Fraction:
    if isinstance(node, ast.Expression):
        return evaluate_node(node.body)
    if isinstance(node, ast.Constant):
        return literal(node.value)
    if isinstance(node, ast.UnaryOp) and type(node.op) in UNARY:
        return UNARY[type(node.op)](evaluate_node(node.operand))
    if isinstance(node, ast.BinOp):
        return binary(node)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in FUNCTIONS:
        if node.keywords:
            raise CalculatorError(f"{node.func.id}() takes no keyword arguments")
        return checked(FUNCTIONS[node.func.id](*(evaluate_node(arg) for arg in node.args)))
    raise CalculatorError(f"unsupported syntax {shorten(ast.unparse(node))!r}; use numbers, + - * / // % **, "
                          f"parentheses and {', '.join(sorted(FUNCTIONS))}()")


def binary(node: ast.BinOp) -> Fraction:
    left, right = evaluate_node(node.left), evaluate_node(node.right)
    if isinstance(node.op, ast.Pow):
        return power(left, right)
    if type(node.op) not in BINARY:
        raise CalculatorError(f"unsupported operator in {shorten(ast.unparse(node))!r}")
    if right == 0 and isinstance(node.op, ast.Div | ast.FloorDiv | ast.Mod):
        raise CalculatorError("division by zero")
    return checked(Fraction(BINARY[type(node.op)](left, right)))


def evaluate(expression: str) -> Fraction:
    """The exact value of ``expression``; :class:`CalculatorError` (a one-line reason) otherwise."""
    if not isinstance(expression, str):
        raise CalculatorError(f"the expression must be text, got {type(expression).__name__}")
    text = expression.strip().replace("^", "**").replace("×", "*").replace("÷", "/")
    if not text:
        raise CalculatorError("the expression is empty")
    if len(text) > MAX_EXPRESSION_CHARS:
        raise CalculatorError(f"the expression is longer than {MAX_EXPRESSION_CHARS} characters")
    try:
        tree = ast.parse(text, mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as error:
        raise CalculatorError(f"cannot parse {shorten(text)!r}: {getattr(error, 'msg', error)}") from None
    if _depth(tree) > MAX_DEPTH:
        raise CalculatorError(f"the expression is nested too deeply (more than {MAX_DEPTH} levels)")
    try:
        return evaluate_node(tree)
    except RecursionError:
        raise CalculatorError("the expression is nested too deeply") from None


def _depth(tree: ast.AST) -> int:
    """How deep the expression's operators nest (iteratively: a deep tree must not recurse here)."""
    deepest, stack = 0, [(tree, 1)]
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        stack.extend((child, depth + 1) for child in ast.iter_child_nodes(node))
    return deepest


def format_number(value: Fraction) -> str:
    """An integer as is; a fraction with a finite decimal expansion of at most
    :data:`MAX_DECIMAL_DIGITS` digits as that decimal; any other fraction as ``p/q`` followed by a
    20-digit approximation."""
    if value.denominator == 1:
        return str(value.numerator)
    denominator = value.denominator
    twos = fives = 0
    while denominator % 2 == 0:
        denominator //= 2
        twos += 1
    while denominator % 5 == 0:
        denominator //= 5
        fives += 1
    places = max(twos, fives)
    # A finite expansion of thousands of digits (2**-9000) would pass Python's int-to-text limit
    # (4300 digits); it is shown as p/q with its approximation instead, like any other fraction.
    if denominator == 1 and places + size_bits(value) * math.log10(2) <= MAX_DECIMAL_DIGITS:
        scaled = value * 10**places  # an integer, by the factorisation above
        sign = "-" if scaled < 0 else ""
        digits = str(abs(scaled.numerator)).rjust(places + 1, "0")
        return f"{sign}{digits[:-places]}.{digits[-places:]}"
    approximate = Decimal(value.numerator) / Decimal(value.denominator)
    return f"{value.numerator}/{value.denominator} ≈ {approximate:.{APPROXIMATE_DIGITS}g}"
