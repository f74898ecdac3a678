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
# optional decimals; or a bare decimal like ".5".
_NUMBER = re.compile(r"[-+]?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?|[-+]?\.\d+")
_ANSWER_LABEL = re.compile(r"answer\s*(?:is)?\s*[:=]\s*", re.IGNORECASE)

AnswerExtractor = Callable[[str], "str | None"]
ANSWER_EXTRACTORS: Registry[AnswerExtractor] = Registry("answer extractor")


def parse_number(text: str | None) -> Fraction | None:
    """Exact value of ``"1,234"``, ``"$18.00"``, ``"-3."``, ``"+07"`` and the like; else None.

    Exact (Fraction, via Decimal) so ``"0.1"`` equals ``"0.10"`` without float rounding surprises.
    Currency signs, percent signs and surrounding punctuation are ignored because GSM8K answers
    and model outputs carry them freely.
    """
    if text is None:
        return None
    cleaned = text.strip().strip("$%,;:!?()[]{} \t\n").rstrip(".").replace(",", "").replace("$", "")
    if not cleaned:
        return None
    try:
        return Fraction(Decimal(cleaned))
    except (InvalidOperation, ValueError):
        return None


@ANSWER_EXTRACTORS.register("marker")
def extract_after_marker(text: str, marker: str = ANSWER_MARKER) -> str | None:
    """The rest of the line after the *last* ``####`` (models sometimes restate the marker)."""
    position = text.rfind(marker)
    if position < 0:
        return None
    tail = text[position + len(marker) :].strip()
    first_line = tail.splitlines()[0].strip() if tail else ""
    return first_line or None


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


@ANSWER_EXTRACTORS.register("last_number")
def extract_last_number(text: str) -> str | None:
    """The last number in the text, commas removed: the most forgiving convention."""
    numbers = _NUMBER.findall(text)
    return numbers[-1].replace(",", "") if numbers else None


def extract_first_number(text: str | None) -> str | None:
    """The first number in ``text`` (used on the short segment after a marker)."""
    if text is None:
        return None
    match = _NUMBER.search(text)
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

