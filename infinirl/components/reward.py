"""Reward component: decodes responses (for scoring only) and runs verifiers in a thread pool.

Running in its own worker lets scoring overlap generation. A verifier that raises gives that
sample reward 0 and an error flag; the run goes on and the count is reported.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from infinirl.engines.base import GenerationResult
from infinirl.runtime import Worker
from infinirl.tasks.problem import Problem
from infinirl.tasks.verifiers import RewardResult, build_verifier, safe_score


def sampled_ids(result: GenerationResult) -> list[int]:
    """The response ids the model wrote: an agent's answer is judged on its own words, not on a
    tool output between its turns (which may well contain the right number)."""
    if result.response_mask is None:
        return result.response_ids
    return [token for token, sampled in zip(result.response_ids, result.response_mask) if sampled]


class RewardWorker(Worker):
    def __init__(self, tokenizer_source: str, verifier: str, format_bonus: float = 0.0, threads: int = 4):
        from transformers import AutoTokenizer

        from infinirl.models.hf_causal_lm import resolve_model_source

        self.tokenizer = AutoTokenizer.from_pretrained(resolve_model_source(tokenizer_source))
        self.verifier = build_verifier(verifier, format_bonus=format_bonus)
        self.pool = ThreadPoolExecutor(max_workers=threads)

    def score(self, results: list[GenerationResult], problems: list[Problem]) -> list[RewardResult]:
        """``problems[i]`` is the problem of ``results[i]`` (the caller repeats per sample)."""
        if len(results) != len(problems):
            raise ValueError(f"score: {len(results)} results but {len(problems)} problems")
        texts = self.tokenizer.batch_decode([sampled_ids(r) for r in results], skip_special_tokens=True)
        return list(self.pool.map(lambda tp: safe_score(tp[0], tp[1], self.verifier), zip(texts, problems)))

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
