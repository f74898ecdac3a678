"""The exact_match verifier: SQuAD normalisation (against SQuAD's own code), answer extraction."""

import random
import re
import string

import pytest

from infinirl.tasks.exact_match import ExactMatchVerifier, extract_tagged_answer, normalize_answer
from infinirl.tasks.problem import Problem
from infinirl.tasks.verifiers import VERIFIERS, get_verifier, safe_score


def squad_normalize(s):
    """SQuAD v1.1's evaluate-v1.1.py normalize_answer, verbatim."""

    def remove_articles(text):
        return re.sub(r"\b(a|an|the)\b", " ", text)

    def white_space_fix(text):
        return " ".join(text.split())

    def remove_punc(text):
        exclude = set(string.punctuation)
        return "".join(ch for ch in text if ch not in exclude)

    def lower(text):
        return text.lower()

    return white_space_fix(remove_articles(remove_punc(lower(s))))


def test_normalisation_matches_squad_on_random_text():
    rng = random.Random(0)
    pieces = ["The", "the", "a", "An", "an", "anchor", "Quenby", "theatre", "A.", "-", "'s", " ", "\t", "\n", ",",
              "1953", "Zekran Works", "(", ")", "!", "é"]
    for _ in range(2000):
        text = "".join(rng.choices(pieces, k=rng.randint(0, 10)))
        assert normalize_answer(text) == squad_normalize(text), repr(text)
    assert normalize_answer("  The  Zekran-Works! ") == "zekranworks"
    assert normalize_answer("an Anchor") == "anchor"


def test_the_answer_is_the_last_answer_tag_else_the_last_line_outside_calls():
    assert extract_tagged_answer("<answer>Quenby</answer>") == "Quenby"
    assert extract_tagged_answer("<answer>x</answer> then <ANSWER> Quenby </answer>\nbye") == "Quenby"
    assert extract_tagged_answer("<search>Mira</search>\n<answer>Quenby") == "Quenby"  # cut before the close
    assert extract_tagged_answer("<search>Mira Tellwood</search>\nShe was born in Quenby.\n\n") == \
        "She was born in Quenby."
    assert extract_tagged_answer("Quenby\n<search>Mira Tellwood</search>") == "Quenby"
    assert extract_tagged_answer("<search>Mira Tellwood</search>") is None
    assert extract_tagged_answer("") is None
    assert extract_tagged_answer("Quenby", fallback="none") is None


def problem(answer, **metadata):
    return Problem(uid="kb/0", prompt="q", answer=answer, verifier="exact_match", metadata=metadata)


def test_exact_match_scores():
    verify = ExactMatchVerifier()
    assert verify("<search>x</search><answer>the Zekran Works.</answer>", problem("Zekran Works")).correct
    assert not verify("<answer>Zekran</answer>", problem("Zekran Works")).correct
    assert verify("Born in 1953\n1953", problem("1953")).reward == 1.0
    assert not verify("Born in 1953, I think", problem("1953")).correct  # exact, not contains
    assert verify("<answer>Kris</answer>", problem("Kris Nanae", aliases=["Kris"])).correct
    strict = ExactMatchVerifier(fallback="none")
    assert not strict("Quenby", problem("Quenby")).correct
    result = verify("<answer>Quenby</answer>", problem("Quenby"))
    assert result.metrics == {"answer_found": 1.0, "answer_tagged": 1.0}
    assert verify("", problem("Quenby")).metrics["answer_found"] == 0.0
    with pytest.raises(ValueError, match="fallback='first'"):
        ExactMatchVerifier(fallback="first")


def test_registered_and_safe_on_bad_gold():
    assert "exact_match" in VERIFIERS
    assert safe_score("<answer>Quenby</answer>", problem("Quenby")).correct
    assert isinstance(get_verifier("exact_match"), ExactMatchVerifier)
    failed = safe_score("<answer>the</answer>", problem("The"))
    assert failed.error and "empty after normalisation" in failed.error and not failed.correct


def test_unicode_punctuation_is_dropped_like_ascii():
    assert normalize_answer("\u201cBrandor Labs\u201d") == "brandor labs"
    assert normalize_answer("Brandor\u2019s \u00abLabs\u00bb\u2014\u2026") == normalize_answer("Brandor's Labs")
    assert ExactMatchVerifier()("<answer>\u201cBrandor Labs\u201d</answer>", problem("Brandor Labs")).correct


def test_answer_tags_mentioned_in_prose_do_not_hide_the_answer():
    response = "I will put the final answer in <answer> tags once sure.\n<answer>Quenby</answer>"
    assert extract_tagged_answer(response) == "Quenby"
    assert ExactMatchVerifier()(response, problem("Quenby")).correct
    assert extract_tagged_answer("The <answer> tag comes last: <answer>Quenby</answer> (an <answer>") == "Quenby"
