"""Pulling the final answer out of free-form model text, and reading numbers robustly.

The answer format is a contract between the prompt instruction (`prompts.py`) and the verifier:
the default instruction asks for the answer after ``####`` (the GSM8K convention, short, one token
pair, and unambiguous), and the ``auto`` extractor below tries that marker first, then the other
common conventions a model may fall back to (``\\boxed{}``, ``Answer:``), then the last number.
Every extractor returns ``None`` when it finds nothing, so "no answer" is never confused with a
wrong one.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from decimal import Decimal, InvalidOperation
from fractions import Fraction

from infinirl.registry import Registry

ANSWER_MARKER = "####"

# A number as people and models write it: optional sign, digits with optional thousands commas,
# optional decimals, or a bare decimal like ".5"; optionally in scientific notation ("2.5e2").
# It is read whole or not at all: digits glued on by a comma, a slash, a point or another digit
# ("1,2345", "3/4", "1.2.3") make no number rather than a truncated one.
_NUMBER_BODY = r"[-+]?(?:(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?|\.\d+)(?:[eE][-+]?\d+)?"
_NUMBER = re.compile(r"(?<![\d.])(?<!\d[,/])" + _NUMBER_BODY + r"(?![\d]|[.,/]\d|[eE][-+]?\d)")
_WHOLE_NUMBER = re.compile(_NUMBER_BODY)
MAX_DECIMAL_EXPONENT = 1000  # "1e999999999" is a number nobody means, and a costly Fraction to build
# Signs other than ASCII '-' that models and typeset sources use: the minus sign and the fullwidth
# and small hyphen-minus always; figure and en dashes only where a sign goes (not in "5–7").
_MINUS_SIGNS = str.maketrans({"\u2212": "-", "\uff0d": "-", "\ufe63": "-"})
_DASH_AS_MINUS = re.compile(r"(?<![\w.])[\u2012\u2013](?=\.?\d)")
_ANSWER_LABEL = re.compile(r"answer\s*(?:is)?\s*[:=]\s*", re.IGNORECASE)
# What follows a markdown heading's "####" rather than an answer: "Step 2: Compute",
# "1. Understanding the Problem", "Final Answer", anything ending in ':'.
_HEADING = re.compile(
    r"(?:step|part|case|stage|phase)\s*\d+\b.*"
    r"|\d+[.)]\s+[^\W\d][^\d]*"
    r"|.*:"
    r"|(?:(?:the|my|final|short|detailed|complete|step[- ]by[- ]step)\s+)*"
    r"(?:answers?|solutions?|explanations?|conclusions?|summary|results?|verification|check|calculations?|"
    r"reasoning|analysis|approach|work|method|steps?|problem|understanding the problem|given|notes?)",
    re.IGNORECASE,
)


def normalize_minus(text: str) -> str:
    """``text`` with typographic minus signs written as ``-``."""
    return _DASH_AS_MINUS.sub("-", text.translate(_MINUS_SIGNS))


AnswerExtractor = Callable[[str], "str | None"]
ANSWER_EXTRACTORS: Registry[AnswerExtractor] = Registry("answer extractor")


def parse_number(text: str | None) -> Fraction | None:
    """Exact value of ``"1,234"``, ``"$18.00"``, ``"-3."``, ``"+07"`` and the like; else None.

    Exact (Fraction, via Decimal) so ``"0.1"`` equals ``"0.10"`` without float rounding surprises.
    Currency signs, percent signs and surrounding punctuation are ignored because GSM8K answers
    and model outputs carry them freely; ``"−5"`` (U+2212) is -5 and ``"2.5e2"`` is 250. A malformed
    number (``"1,2345"``, ``"3/4"``) or one beyond 1e±1000 is None.
    """
    if text is None:
        return None
    cleaned = normalize_minus(text).strip().strip("$%,;:!?()[]{} \t\n").rstrip(".").replace("$", "")
    if not _WHOLE_NUMBER.fullmatch(cleaned):
        return None
    try:
        value = Decimal(cleaned.replace(",", ""))
    except (InvalidOperation, ValueError):
        return None
    if value and abs(value.adjusted()) > MAX_DECIMAL_EXPONENT:
        return None
    return Fraction(value)


@ANSWER_EXTRACTORS.register("marker")
def extract_after_marker(text: str, marker: str = ANSWER_MARKER) -> str | None:
    """The rest of the line after the last ``####`` followed by an answer (models sometimes restate
    the marker). A markdown heading (``#### Step 2: Compute``, ``#### Final Answer``) is not one:
    see `_HEADING`; with no answer after any marker, None, so ``auto`` goes on to ``\\boxed{}``."""
    end = len(text)
    while (position := text.rfind(marker, 0, end)) >= 0:
        end = position
        tail = text[position + len(marker) :].strip()
        first_line = tail.splitlines()[0].strip() if tail else ""
        if first_line and not _HEADING.fullmatch(first_line):
            return first_line
    return None


@ANSWER_EXTRACTORS.register("boxed")
def extract_boxed(text: str) -> str | None:
    """Content of the last ``\\boxed{...}`` (or ``\\fbox{...}``), braces balanced."""
    start = max(text.rfind("\\boxed{"), text.rfind("\\fbox{"))
    if start < 0:
        return None
    position = text.index("{", start) + 1
    depth = 1
    for end in range(position, len(text)):
        if text[end] == "{":
            depth += 1
        elif text[end] == "}":
            depth -= 1
            if depth == 0:
                return text[position:end].strip() or None
    return None  # unbalanced: the response was cut off inside the box


@ANSWER_EXTRACTORS.register("answer_label")
def extract_after_answer_label(text: str) -> str | None:
    """The rest of the line after the last ``Answer:`` / ``answer is:`` / ``Answer =``."""
    matches = list(_ANSWER_LABEL.finditer(text))
    if not matches:
        return None
    tail = text[matches[-1].end() :].strip()
    first_line = tail.splitlines()[0].strip() if tail else ""
    return first_line or None


def find_numbers(text: str) -> list[str]:
    """Every number in ``text`` (see `_NUMBER`), in order, commas removed and minus signs as ``-``."""
    return [number.replace(",", "") for number in _NUMBER.findall(normalize_minus(text))]


@ANSWER_EXTRACTORS.register("last_number")
def extract_last_number(text: str) -> str | None:
    """The last number in the text, commas removed: the most forgiving convention."""
    numbers = find_numbers(text)
    return numbers[-1] if numbers else None


def extract_first_number(text: str | None) -> str | None:
    """The first number in ``text`` (used on the short segment after a marker)."""
    if text is None:
        return None
    match = _NUMBER.search(normalize_minus(text))
    return match.group(0).replace(",", "") if match else None


@ANSWER_EXTRACTORS.register("auto")
def extract_answer_auto(text: str) -> str | None:
    """Marker, then ``\\boxed{}``, then ``Answer:``, then the last number: first one found wins."""
    for extractor in (extract_after_marker, extract_boxed, extract_after_answer_label):
        found = extractor(text)
        if found is not None:
            return found
    return extract_last_number(text)


def get_answer_extractor(name: str) -> AnswerExtractor:
    """Look an extractor up by name; the error lists the valid names."""
    return ANSWER_EXTRACTORS.get(name)

