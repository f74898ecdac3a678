"""Exact match of a short text answer, SQuAD-style: the ``exact_match`` verifier.

The answer is read from the model's own text: the content of its last ``<answer>...</answer>``;
without one (``fallback="last_line"``, the default) the last non-empty line once complete tag pairs
(``<search>...</search>`` calls) are removed, so a model that answers in plain words is still read.
Both sides are normalised as SQuAD's evaluation does (lowercase, punctuation and the articles a / an
/ the removed, whitespace collapsed; Unicode punctuation such as curly quotes is removed too) and
compared; the problem's ``metadata["aliases"]`` are further
accepted answers.
"""

from __future__ import annotations

import re
import string
import unicodedata
from dataclasses import dataclass

from infinirl.tasks.problem import Problem
from infinirl.tasks.verifiers import VERIFIERS, RewardResult

__all__ = ["ExactMatchVerifier", "extract_tagged_answer", "normalize_answer"]

# A pair's content holds no further "<answer>": an opening tag mentioned in prose before the real
# pair ("I'll use <answer> tags") is not where the answer starts.
ANSWER_PAIR = re.compile(r"<answer>((?:(?!<answer>).)*?)</answer>", re.DOTALL | re.IGNORECASE)
UNCLOSED_ANSWER = re.compile(r"<answer>((?:(?!<answer>).)*)\Z", re.DOTALL | re.IGNORECASE)
TAG_PAIR = re.compile(r"<(\w+)>.*?</\1>", re.DOTALL)
ARTICLES = re.compile(r"\b(a|an|the)\b")
PUNCTUATION = frozenset(string.punctuation)
FALLBACKS = ("last_line", "none")


def normalize_answer(text: str) -> str:
    """SQuAD's normalisation: lowercase, drop punctuation, drop articles, collapse whitespace.
    Punctuation is ASCII's and Unicode's (curly quotes, dashes, ellipses), so a typographic
    ``“Brandor Labs”`` matches ``Brandor Labs`` as the ASCII-quoted one does."""
    text = "".join(ch for ch in text.lower() if ch not in PUNCTUATION and not unicodedata.category(ch).startswith("P"))
    return " ".join(ARTICLES.sub(" ", text).split())


def extract_tagged_answer(text: str, fallback: str = "last_line") -> str | None:
    """The last complete ``<answer>...</answer>`` pair's content, else an ``<answer>`` left open at
    the end (a response cut off); else, with ``fallback="last_line"``, the last non-empty line
    outside complete tag pairs; else ``None``."""
    tagged = _tagged_answer(text)
    if tagged is not None:
        return tagged
    if fallback == "none":
        return None
    lines = [line.strip() for line in TAG_PAIR.sub("\n", text).splitlines() if line.strip()]
    return lines[-1] if lines else None


def _tagged_answer(text: str) -> str | None:
    pairs = ANSWER_PAIR.findall(text)
    if pairs:
        return pairs[-1].strip()
    unclosed = UNCLOSED_ANSWER.search(text)
    return unclosed.group(1).strip() if unclosed else None


@VERIFIERS.register("exact_match")
@dataclass(frozen=True)
class ExactMatchVerifier:
    """Reward 1 when the normalised answer equals the normalised gold answer (or an alias).

    ``fallback``: ``last_line`` reads an untagged answer from the last line; ``none`` scores a
    response without ``<answer>`` as wrong (a stricter format)."""

    fallback: str = "last_line"

    def __post_init__(self) -> None:
        if self.fallback not in FALLBACKS:
            raise ValueError(f"exact_match fallback={self.fallback!r}: use one of {', '.join(FALLBACKS)}")

    def __call__(self, response: str, problem: Problem) -> RewardResult:
        answers = [problem.answer, *problem.metadata.get("aliases", ())]
        golds = {normalize_answer(answer) for answer in answers} - {""}
        if not golds:
            raise ValueError(f"exact_match verifier: the gold answer {problem.answer!r} of {problem.uid} is empty "
                             "after normalisation")
        candidate = extract_tagged_answer(response, self.fallback)
        correct = candidate is not None and normalize_answer(candidate) in golds
        tagged = _tagged_answer(response) is not None
        return RewardResult(float(correct), correct,
                            metrics={"answer_found": float(candidate is not None), "answer_tagged": float(tagged)})
