"""Reward component: decodes responses (for scoring only) and runs verifiers in a thread pool.

Running in its own worker lets scoring overlap generation. A verifier that raises gives that
sample reward 0 and an error flag; the run goes on and the count is reported.

Each problem is scored by the verifier it names (``Problem.verifier``): the task source decides it
(a GSM8K preset's rows name ``gsm8k``, generated code tasks ``code_tests``), and a batch may mix
sources. The configured verifier serves problems that name none.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

from infinirl.engines.base import GenerationResult
from infinirl.runtime import Worker
from infinirl.tasks.problem import Problem
from infinirl.tasks.verifiers import RewardResult, Verifier, build_verifier, safe_score


def sampled_ids(result: GenerationResult) -> list[int]:
    """The response ids the model wrote: an agent's answer is judged on its own words, not on a
    tool output between its turns (which may well contain the right number)."""
    if result.response_mask is None:
        return result.response_ids
    return [token for token, sampled in zip(result.response_ids, result.response_mask) if sampled]


class ProblemVerifiers:
    """The verifier of each problem, built on first use per name (with the run's format bonus for
    the task's answer format, ``task.answer_format``) and
    kept: a verifier may hold state worth reusing (a loaded user function, parsed answers)."""

    def __init__(self, default: str, format_bonus: float = 0.0, answer_format: str = "marker"):
        self.default, self.format_bonus, self.answer_format = default, format_bonus, answer_format
        # The configured name is built now: a bad one fails when the worker starts.
        self._built: dict[str, Verifier] = {default: self._build(default)}

    def _build(self, name: str) -> Verifier:
        return build_verifier(name, format_bonus=self.format_bonus, answer_format=self.answer_format)

    def get(self, name: str | None) -> Verifier:
        """The verifier ``name`` (the configured one for ``None`` or ``""``). A name that cannot be
        built gives a verifier raising that error, so each of its samples is a counted verifier
        error (reward 0), as with a verifier that raises."""
        name = name or self.default
        if name not in self._built:
            try:
                self._built[name] = self._build(name)
            except Exception as error:  # noqa: BLE001 - reported per sample, like a failing verifier
                self._built[name] = _failing(f"verifier {name!r} cannot be built: {type(error).__name__}: {error}")
        return self._built[name]

    def score(self, texts: Sequence[str], problems: Sequence[Problem], pool: ThreadPoolExecutor) -> list[RewardResult]:
        """``texts[i]`` scored against ``problems[i]``. Verifiers are looked up (and built) here,
        before the pool's threads score with them."""
        chosen = [self.get(problem.verifier) for problem in problems]
        return list(pool.map(safe_score, texts, problems, chosen))


def _failing(message: str) -> Verifier:
    def verifier(response: str, problem: Problem) -> RewardResult:
        raise ValueError(message)

    return verifier


class RewardWorker(Worker):
    def __init__(self, tokenizer_source: str, verifier: str, format_bonus: float = 0.0, answer_format: str = "marker",
                 threads: int = 4):
        from transformers import AutoTokenizer

        from infinirl.models.hf_causal_lm import resolve_model_source

        self.tokenizer = AutoTokenizer.from_pretrained(resolve_model_source(tokenizer_source))
        self.verifiers = ProblemVerifiers(verifier, format_bonus, answer_format)
        self.pool = ThreadPoolExecutor(max_workers=threads)

    def score(self, results: list[GenerationResult], problems: list[Problem]) -> list[RewardResult]:
        """``problems[i]`` is the problem of ``results[i]`` (the caller repeats per sample)."""
        if len(results) != len(problems):
            raise ValueError(f"score: {len(results)} results but {len(problems)} problems")
        texts = self.tokenizer.batch_decode([sampled_ids(r) for r in results], skip_special_tokens=True)
        return self.verifiers.score(texts, problems, self.pool)

    def score_stream(self, source, sink, problems: dict[int, list[Problem]], count: int, key: str = "default") -> int:
        """Take ``count`` generated chunks ``(index, results)`` from ``source`` under ``key``
        (whichever arrive first: several reward ranks share one source), score them, put ``(index,
        results, rewards)`` into ``sink`` under the same key. ``problems[index]`` lists the problem of
        each result of a chunk."""
        for _ in range(count):
            index, results = source.get(key=key)
            sink.put((index, results, self.score(results, problems[index])), key=key, weight=len(results))
        sink.flush()
        return count
