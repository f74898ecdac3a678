"""Answer extraction and number parsing against many hand-written model outputs."""

from fractions import Fraction

import pytest

from infinirl.tasks.answers import (
    extract_after_answer_label,
    extract_after_marker,
    extract_answer_auto,
    extract_boxed,
    extract_last_number,
    get_answer_extractor,
    parse_number,
)
from infinirl.tasks.datasets import extract_gsm8k_gold


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("42", Fraction(42)),
        ("1,234", Fraction(1234)),
        ("1,234,567.50", Fraction(123456750, 100)),
        ("$18.00", Fraction(18)),
        ("-3.", Fraction(-3)),
        ("+07", Fraction(7)),
        ("0.10", Fraction(1, 10)),
        (" 5% ", Fraction(5)),
        (".5", Fraction(1, 2)),
        ("twelve", None),
        ("", None),
        (None, None),
        ("3/4", None),  # fractions are not GSM8K-style numbers; the math verifier handles them
    ],
)
def test_parse_number(text, value):
    assert parse_number(text) == value


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("He pays 3 * 6 = 18 dollars.\n#### 18", "18"),
        ("#### 1,000", "1,000"),
        ("#### 5\nextra text\n#### 7 apples", "7 apples"),  # last marker wins, one line only
        ("no marker here 12", None),
        ("####   \n", None),
        ("####-3", "-3"),
    ],
)
def test_extract_after_marker(response, expected):
    assert extract_after_marker(response) == expected


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("so \\boxed{42}.", "42"),
        ("\\boxed{1} then \\boxed{\\frac{1}{2}}", "\\frac{1}{2}"),
        ("\\boxed{\\left( 3, \\frac{\\pi}{2} \\right)}", "\\left( 3, \\frac{\\pi}{2} \\right)"),
        ("\\fbox{7}", "7"),
        ("cut off \\boxed{\\frac{1}{", None),
        ("nothing", None),
    ],
)
def test_extract_boxed(response, expected):
    assert extract_boxed(response) == expected


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("Answer: 12", "12"),
        ("The answer is: -4 apples", "-4 apples"),
        ("answer = 9", "9"),
        ("no label 3", None),
    ],
)
def test_extract_after_answer_label(response, expected):
    assert extract_after_answer_label(response) == expected


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("3 + 4 = 7", "7"),
        ("It costs $1,250.50 in total.", "1250.50"),
        ("from -3 to -12.", "-12"),
        ("no digits", None),
    ],
)
def test_extract_last_number(response, expected):
    assert extract_last_number(response) == expected


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("work 5 \\boxed{6} #### 7", "7"),  # marker beats box
        ("work 5 \\boxed{6} Answer: 8", "6"),  # box beats label
        ("work 5 Answer: 8 more 9", "8 more 9"),  # label beats last number
        ("work 5 then 9", "9"),
        ("nothing at all", None),
    ],
)
def test_auto_extraction_order(response, expected):
    assert extract_answer_auto(response) == expected


def test_unknown_extractor_lists_valid_names():
    with pytest.raises(KeyError, match="last_number"):
        get_answer_extractor("first_guess")


@pytest.mark.parametrize(
    ("solution", "gold"),
    [
        ("Janet sells 9 eggs.\nShe makes 9 * 2 = $<<9*2=18>>18.\n#### 18", "18"),
        ("big\n#### 1,600", "1600"),
        ("neg\n#### -5", "-5"),
    ],
)
def test_gsm8k_gold_extraction(solution, gold):
    assert extract_gsm8k_gold(solution) == gold


def test_gsm8k_gold_without_marker_is_an_error():
    with pytest.raises(ValueError, match="no '#### <answer>' line"):
        extract_gsm8k_gold("a solution with no final line 12")
