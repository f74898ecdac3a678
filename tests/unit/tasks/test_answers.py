"""Answer extraction and number parsing against many hand-written model outputs."""

from fractions import Fraction

import pytest

from infinirl.tasks.answers import (
    MARKER_WINDOW,
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


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        # The prompt's instruction echoed after the answer: its marker is in quotes.
        ("#### 42\nGive the final answer after '####'.", "42"),
        ('#### 42\nGive the final answer after "####".', "42"),
        ("#### 42\nI wrote it after `####` as asked", "42"),
        ("#### 42\nThe answer goes after ####.", "42"),  # nothing but punctuation after the marker
        ("#### 42\n#### ?", "42"),
        ("#### ?", None),
    ],
)
def test_echoed_or_empty_markers_do_not_hide_the_answer(response, expected):
    assert extract_after_marker(response) == expected


@pytest.mark.parametrize(
    ("response", "number"),
    [
        ("#### 18. That is the final answer.", "18"),
        ("#### 18. Done", "18"),
        ("#### 18) apples", "18"),
        ("The total is 18.\n#### 18. Done\n", "18"),
    ],
)
def test_an_answer_followed_by_words_is_not_a_numbered_heading(response, number):
    assert extract_first_number(extract_after_marker(response)) == number


@pytest.mark.parametrize(
    "response",
    [
        "#### 1. Understanding the Problem\nwe need 5",
        "#### 2) Set Up the Equation\nx = 5",
        "#### 3. Compute\n5 + 5",
    ],
)
def test_numbered_headings_with_text_after_them_are_not_answers(response):
    assert extract_after_marker(response) is None


@pytest.mark.parametrize(
    ("response", "expected"),
    [
        ("<answer>42</answer>\nI verified it in 3 steps.", "42"),
        ("<answer>olleh</answer>", "olleh"),
        ("<answer>1</answer> no, <answer> 2 </answer>", "2"),
        ("To get the answer: 4 + 3 = 7", "7"),
        ("The answer is: x = 7", "7"),
        ("Answer: x = y + 1", "x = y + 1"),  # no number after '=': the line as written
    ],
)
def test_auto_reads_answer_tags_and_the_result_of_a_labelled_sum(response, expected):
    assert extract_answer_auto(response) == expected


@pytest.mark.parametrize(
    ("segment", "first", "value"),
    [
        ("-$5", "-5", Fraction(-5)),
        ("\u2212$5.50 loss", "-5.50", Fraction(-11, 2)),
        ("+$3", "+3", Fraction(3)),
        ("10-$3", "10", Fraction(10)),  # a subtraction, not a sign
        ("1 000", "1000", Fraction(1000)),
        ("1\u2009000", "1000", Fraction(1000)),
        ("-1\u202f234\u202f567.5 m", "-1234567.5", Fraction(-2469135, 2)),
        ("1 0000", "1", Fraction(1)),  # not groups of three: no thousands separator
        ("3 apples, 100 pears", "3", Fraction(3)),
    ],
)
def test_signs_before_currency_and_space_grouped_thousands(segment, first, value):
    assert extract_first_number(segment) == first
    assert parse_number(first) == value


def test_gsm8k_reads_a_negative_amount_and_space_grouped_thousands():
    from infinirl.tasks.problem import Problem
    from infinirl.tasks.verifiers import Gsm8kVerifier

    verifier = Gsm8kVerifier()
    assert verifier("She lost money.\n#### -$5", Problem(uid="a", prompt="q", answer="-5", verifier="gsm8k")).correct
    assert verifier("#### 1 000", Problem(uid="b", prompt="q", answer="1000", verifier="gsm8k")).correct


def test_many_markers_are_each_read_within_a_bounded_window():
    # 8000 headings, then the answer: every marker is looked at, each through a short window only.
    headings = "\n".join(f"#### Step {i}" for i in range(8000))
    assert extract_after_marker(headings + "\n#### 42") == "42"
    assert extract_after_marker("#### 7\n" + headings) == "7"
    # A line longer than the window is cut at it rather than scanned to its end.
    assert extract_after_marker("#### 5 " + "x" * 100_000) == (" 5 " + "x" * 100_000)[:MARKER_WINDOW].strip()
