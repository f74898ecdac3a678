"""The calculator is exact, refuses everything that is not arithmetic, and cannot be made to hang."""

from fractions import Fraction

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from infinirl.agents.calculator import MAX_EXPRESSION_CHARS, CalculatorError, evaluate, format_number


@st.composite
def expressions(draw, depth=3):
    """(text, exact value) pairs built side by side: the value is the reference, not a parse of the text."""
    if depth == 0 or draw(st.booleans()):
        number = draw(st.integers(-10**12, 10**12))
        return (f"({number})" if number < 0 else str(number)), Fraction(number)
    left_text, left = draw(expressions(depth=depth - 1))
    right_text, right = draw(expressions(depth=depth - 1))
    op = draw(st.sampled_from("+-*/"))
    if op == "/" and right == 0:
        op = "*"
    value = {"+": left + right, "-": left - right, "*": left * right, "/": left / right if right else 0}[op]
    return f"({left_text} {op} {right_text})", value


@settings(max_examples=300, deadline=None)
@given(expressions())
def test_matches_exact_reference(case):
    text, value = case
    assert evaluate(text) == value


@pytest.mark.parametrize("text, shown", [
    ("123456789 * 987654321", "121932631112635269"),
    ("0.1 + 0.2", "0.3"),
    ("7 / 3", "7/3 ≈ 2.3333333333333333333"),
    ("2 ** -3", "0.125"),
    ("-7 // 2", "-4"),
    ("7 % 3", "1"),
    ("3^2", "9"),
    ("2.5e-3", "0.0025"),
    ("-0.05", "-0.05"),
    ("round(7 / 3, 4)", "2.3333"),
    ("abs(-3.5) + max(1, 2) - min(4, 5)", "1.5"),
    ("(-1) ** 1000001", "-1"),
])
def test_known_values(text, shown):
    assert format_number(evaluate(text)) == shown


@pytest.mark.parametrize("text, message", [
    ("10**10**10", "digits"),
    ("9**9**9", "digits"),
    ("(10**2000) * (10**2000)", "bits"),
    ("1 / 0", "division by zero"),
    ("5 % 0", "division by zero"),
    ("0 ** -1", "division by zero"),
    ("2 ** 0.5", "integer exponents"),
    ("__import__('os').system('true')", "unsupported syntax"),
    ("open('/etc/passwd')", "unsupported syntax"),
    ("x + 1", "unsupported syntax"),
    ("'a' * 3", "only numbers"),
    ("True + 1", "only numbers"),
    ("[1, 2]", "unsupported syntax"),
    ("1 +", "cannot parse"),
    ("", "empty"),
    ("1" * (MAX_EXPRESSION_CHARS + 1), "longer than"),
    ("(" * 300 + "1" + ")" * 300, "cannot parse"),
    ("1" + "+1" * 499, "nested too deeply"),
    ("min()", "at least one"),
    ("round(1, 2, 3)", "round()"),
    ("abs(x=1)", "keyword"),
    ("1 << 2", "unsupported operator"),
])
def test_refusals_are_clear(text, message):
    with pytest.raises(CalculatorError, match=message):
        evaluate(text)


def test_non_text_is_refused():
    with pytest.raises(CalculatorError, match="must be text"):
        evaluate(12)  # type: ignore[arg-type]


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=60))
def test_any_text_is_a_value_or_a_calculator_error(text):
    try:
        evaluate(text)
    except CalculatorError:
        pass


@pytest.mark.parametrize("text, value", [
    ("2 ** -9000", Fraction(1, 2**9000)),
    ("2 ** -6500", Fraction(1, 2**6500)),  # 4543 digits
    ("(2 ** 9000 + 1) / 2 ** 9000", Fraction(2**9000 + 1, 2**9000)),
    ("-(5 ** 4000) / 2 ** 4000", Fraction(-(5**4000), 2**4000)),
])
def test_decimals_too_long_to_print_fall_back_to_the_fraction(text, value):
    """A finite decimal expansion of thousands of digits (past Python's int-to-text limit) is shown
    as p/q with its approximation, never as the interpreter's error."""
    shown = format_number(evaluate(text))
    exact, approximate = shown.split(" ≈ ")
    assert Fraction(exact) == value
    assert abs(Fraction(approximate) / value - 1) < Fraction(1, 10**18)


def test_long_finite_decimals_below_the_bound_are_still_printed_in_full():
    assert format_number(evaluate("2 ** -3000")) == f"0.{5**3000:0>3000}"


def test_the_calculator_tool_answers_a_tiny_power():
    import asyncio

    from infinirl.agents.tools import CalculatorTool, call_tool

    result = asyncio.run(call_tool(CalculatorTool(), {"expression": "2**-9000"}))
    assert result.ok and "set_int_max_str_digits" not in result.text and result.text.startswith("1/"), result
