"""Pulling the final answer out of free-form model text, and reading numbers robustly.

The answer format is a contract between the prompt instruction (`prompts.py`) and the verifier:
the default instruction asks for the answer after ``####`` (the GSM8K convention, short, one token
pair, and unambiguous), and the ``auto`` extractor below tries that marker first, then the other
common conventions a model may fall back to (``<answer>`` tags, ``\\boxed{}``, ``Answer:``), then
the last number.
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

# A number as people and models write it: optional sign, digits with optional thousands separators
# (commas, or the thin / no-break spaces of typeset text, one kind per number), optional decimals,
# or a bare decimal like ".5"; optionally in scientific notation ("2.5e2").
# It is read whole or not at all: digits glued on by a comma, a slash, a point or another digit
# ("1,2345", "3/4", "1.2.3") make no number rather than a truncated one.
_THIN_SPACES = "\u2009\u202f\u00a0"
_GROUPED = r"\d{1,3}(?:,\d{3})+|\d{1,3}(?:[" + _THIN_SPACES + r"]\d{3})+"
_NUMBER_BODY = r"[-+]?(?:(?:" + _GROUPED + r"|\d+)(?:\.\d+)?|\.\d+)(?:[eE][-+]?\d+)?"
_NUMBER = re.compile(r"(?<![\d.])(?<!\d[,/" + _THIN_SPACES + r"])" + _NUMBER_BODY
                     + r"(?![\d]|[.,/" + _THIN_SPACES + r"]\d|[eE][-+]?\d)")
# In the short segment after an answer marker ("#### 1 000") plain spaces group thousands too; in
# running text "2 100-page books" they would glue two numbers together, so only there.
_SPACE_GROUPED_NUMBER = re.compile(r"(?<![\d.,])[-+]?\d{1,3}(?: \d{3})+(?:\.\d+)?(?![\d]|[ .,/]\d)")
_WHOLE_NUMBER = re.compile(_NUMBER_BODY)
_SEPARATORS = str.maketrans("", "", "," + _THIN_SPACES)
# A currency sign between the sign and the digits ("-$5"): the sign belongs to the number. Only a
# sign that starts a word: in "10-$3" the '-' is a subtraction.
_SIGN_BEFORE_CURRENCY = re.compile(r"(?<![\w.])([-+])[$\u20ac\u00a3\u00a5](?=\.?\d)")
MAX_DECIMAL_EXPONENT = 1000  # "1e999999999" is a number nobody means, and a costly Fraction to build
# Signs other than ASCII '-' that models and typeset sources use: the minus sign and the fullwidth
# and small hyphen-minus always; figure and en dashes only where a sign goes (not in "5–7").
_MINUS_SIGNS = str.maketrans({"\u2212": "-", "\uff0d": "-", "\ufe63": "-"})
_DASH_AS_MINUS = re.compile(r"(?<![\w.])[\u2012\u2013](?=\.?\d)")
_ANSWER_LABEL = re.compile(r"answer\s*(?:is)?\s*[:=]\s*", re.IGNORECASE)
# How far after a marker its answer line is read: an answer is short, and reading a bounded window
# per marker keeps a response with thousands of markers linear to scan.
MARKER_WINDOW = 500
_QUOTES = "'\"`\u2018\u2019\u201c\u201d\u00ab\u00bb"
# What follows a markdown heading's "####" rather than an answer: "Step 2: Compute",
# "Final Answer", anything ending in ':'. A numbered title ("1. Understanding the Problem") is
# matched by `_NUMBERED_HEADING` and only counts as a heading with more text after it.
_HEADING = re.compile(
    r"(?:step|part|case|stage|phase)\s*\d+\b.*"
    r"|.*:"
    r"|(?:(?:the|my|final|short|detailed|complete|step[- ]by[- ]step)\s+)*"
    r"(?:answers?|solutions?|explanations?|conclusions?|summary|results?|verification|check|calculations?|"
    r"reasoning|analysis|approach|work|method|steps?|problem|understanding the problem|given|notes?)",
    re.IGNORECASE,
)
# A numbered title: a small number, then at most six words starting with a capital, no digits, and
# no closing full stop (which "18. That is the final answer." has, and "18) apples" has no capital).
_NUMBERED_HEADING = re.compile(r"\d{1,2}[.)]\s+[A-Z][^\W\d]*(?:[ \-&/,]+[^\W\d]+){0,5}")


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
        value = Decimal(cleaned.translate(_SEPARATORS))
    except (InvalidOperation, ValueError):
        return None
    if value and abs(value.adjusted()) > MAX_DECIMAL_EXPONENT:
        return None
    return Fraction(value)


@ANSWER_EXTRACTORS.register("marker")
def extract_after_marker(text: str, marker: str = ANSWER_MARKER) -> str | None:
    """The rest of the line after the last ``####`` followed by an answer (models sometimes restate
    the marker). Not one: a markdown heading (``#### Step 2: Compute``, ``#### Final Answer``, see
    `_HEADING`; a numbered title such as ``#### 1. Setup`` only with more text after it), a marker
    in quotes (an echoed instruction: ``Give the final answer after '####'.``) and a marker
    followed by no letter or digit (``#### ?``). With no answer after any marker, None, so ``auto``
    goes on to ``\\boxed{}``. Only `MARKER_WINDOW` characters after each marker are read."""
    content_end = len(text.rstrip())
    end = len(text)
    while (position := text.rfind(marker, 0, end)) >= 0:
        end = position
        if _quoted(text, position, position + len(marker)):
            continue
        start = position + len(marker)
        window = text[start : start + MARKER_WINDOW]
        offset = len(window) - len(window.lstrip())
        first_line = window[offset:].split("\n", 1)[0].strip()
        if not first_line or not any(char.isalnum() for char in first_line) or _HEADING.fullmatch(first_line):
            continue
        line_end = start + offset + len(window[offset:].split("\n", 1)[0])
        if _NUMBERED_HEADING.fullmatch(first_line) and line_end < content_end:
            continue
        return first_line
    return None


def _quoted(text: str, start: int, end: int) -> bool:
    """Whether ``text[start:end]`` sits in quotes: a quote right before it or right after it."""
    return (start > 0 and text[start - 1] in _QUOTES) or (end < len(text) and text[end] in _QUOTES)


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


@ANSWER_EXTRACTORS.register("tagged")
def extract_tagged(text: str) -> str | None:
    """Content of the last ``<answer>...</answer>`` (reasoning-gym's own answer format)."""
    lowered = text.lower()  # two reverse searches: linear even with many unclosed tags
    end = lowered.rfind("</answer>")
    start = lowered.rfind("<answer>", 0, end) if end >= 0 else -1
    return (text[start + len("<answer>") : end].strip() or None) if start >= 0 else None


@ANSWER_EXTRACTORS.register("answer_label")
def extract_after_answer_label(text: str) -> str | None:
    """The rest of the line after the last ``Answer:`` / ``answer is:`` / ``Answer =``; when that
    line is a worked expression ending in ``= <number>`` (``4 + 3 = 7``), that number."""
    matches = list(_ANSWER_LABEL.finditer(text))
    if not matches:
        return None
    tail = text[matches[-1].end() :].strip()
    first_line = tail.splitlines()[0].strip() if tail else ""
    if "=" in first_line:
        result = first_line.rsplit("=", 1)[1].strip()
        if parse_number(result) is not None:
            return result
    return first_line or None


def find_numbers(text: str) -> list[str]:
    """Every number in ``text`` (see `_NUMBER`), in order, commas removed and minus signs as ``-``."""
    return [number.translate(_SEPARATORS) for number in _NUMBER.findall(_normalize_signs(text))]


def _normalize_signs(text: str) -> str:
    """Typographic minus signs as ``-``, and a currency sign after a sign dropped (``-$5``: ``-5``)."""
    return _SIGN_BEFORE_CURRENCY.sub(r"\1", normalize_minus(text))


@ANSWER_EXTRACTORS.register("last_number")
def extract_last_number(text: str) -> str | None:
    """The last number in the text, commas removed: the most forgiving convention."""
    numbers = find_numbers(text)
    return numbers[-1] if numbers else None


def extract_first_number(text: str | None) -> str | None:
    """The first number in ``text`` (used on the short segment after a marker), separators removed;
    here plain spaces group thousands too (``1 000``)."""
    if text is None:
        return None
    text = _normalize_signs(text)
    matches = [match for match in (_NUMBER.search(text), _SPACE_GROUPED_NUMBER.search(text)) if match]
    if not matches:
        return None
    # The earliest; at one start the longer ("1 000" over "1").
    first = min(matches, key=lambda match: (match.start(), -len(match.group(0))))
    return first.group(0).translate(_SEPARATORS).replace(" ", "")


@ANSWER_EXTRACTORS.register("auto")
def extract_answer_auto(text: str) -> str | None:
    """Marker, then ``<answer>`` tags, then ``\\boxed{}``, then ``Answer:``, then the last number:
    first one found wins."""
    for extractor in (extract_after_marker, extract_tagged, extract_boxed, extract_after_answer_label):
        found = extractor(text)
        if found is not None:
            return found
    return extract_last_number(text)


def get_answer_extractor(name: str) -> AnswerExtractor:
    """Look an extractor up by name; the error lists the valid names."""
    return ANSWER_EXTRACTORS.get(name)

