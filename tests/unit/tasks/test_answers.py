"""Answer extraction and number parsing against many hand-written model outputs."""

from fractions import Fraction

import pytest

from infinirl.tasks.answers import (
    extract_after_answer_label,
    extract_after_marker,
    extract_answer_auto,
    extract_boxed,
    extract_first_number,
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


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("#### Step 1: Read\nThere are 3 boxes.\n#### Step 2: Compute\nThe result is 99.", None),
        ("#### Final Answer\n\\boxed{42}", None),
        ("#### Final Answer:\n42", None),
        ("#### 1. Understanding the Problem\nwe need 5", None),
        ("#### Solution\nIt is 3", None),
        ("#### 42\n\n#### Verification\nchecked", "42"),  # the last marker followed by an answer counts
        ("#### The sum is 42.", "The sum is 42."),
        ("#### Answer: 42", "Answer: 42"),
        ("#### seven", "seven"),
        ("#### True", "True"),
        ("####\n12", "12"),
    ],
)
def test_markdown_headings_are_not_answer_markers(response, expected):
    assert extract_after_marker(response) == expected


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("#### Final Answer\n\\boxed{42}", "42"),
        ("#### Final Answer\n\nThe answer is: 42", "42"),
        ("#### Step 1: Read\n...\n#### Step 2: Compute\nThe result is 99.", "99"),
    ],
)
def test_auto_extraction_falls_back_past_headings(response, expected):
    assert extract_answer_auto(response) == expected


@pytest.mark.parametrize(
    ("text", "first", "value"),
    [
        ("\u22125", "-5", Fraction(-5)),  # U+2212 MINUS SIGN
        ("\u20135 degrees", "-5", Fraction(-5)),  # an en dash used as a minus
        ("\uff0d7", "-7", Fraction(-7)),
        ("pages 5\u20137", "5", Fraction(5)),  # an en dash in a range is not a sign
        ("3/4", None, None),
        ("1e3", "1e3", Fraction(1000)),
        ("2.5e2 m", "2.5e2", Fraction(250)),
        ("-1.5E-2", "-1.5E-2", Fraction(-3, 200)),
        ("1,2345", None, None),
        ("1,23", None, None),
        ("1,234", "1234", Fraction(1234)),
        ("1,234.5 kg", "1234.5", Fraction(2469, 2)),
        ("12,345,678", "12345678", Fraction(12345678)),
        ("7, then 8", "7", Fraction(7)),
        ("1.2.3", None, None),
        ("1e999999999", "1e999999999", None),  # an absurd exponent is not a value worth building
        ("inf", None, None),
    ],
)
def test_numbers_read_whole_or_not_at_all(text, first, value):
    assert extract_first_number(text) == first
    assert parse_number(first if first is not None else text) == value
