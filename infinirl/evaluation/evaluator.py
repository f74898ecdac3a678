"""Generate over the rollout ranks, score in the reward workers, and aggregate into metrics.

Prompts are cut into calls of ``max_batch_size // n`` prompts; each rollout rank takes the next
call as soon as it is free (uneven response lengths do not leave ranks idle), and each finished
call is scored by a reward worker while the rank generates its next one. A call's sampling seed
depends only on its position in the work list, so results do not depend on the number of ranks.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections import deque
from dataclasses import dataclass

import numpy as np

from infinirl.engines.base import SamplingParams
from infinirl.evaluation.passk import mean_pass_at_k
from infinirl.tasks.problem import Problem


@dataclass
class PassResult:
    """One decoding pass (greedy, or ``n`` samples) over all problems: correctness per sample."""

    n: int
    correct: list[list[bool]]
    """``correct[i][j]``: sample j of problem i."""
    responses: list[list[str]]
    """Decoded responses, kept only for the greedy pass (for reading failures)."""
    logprobs: list[list[float]]
    """Summed token log-probs of those responses (how sure the model was; differs between weights)."""
    errors: int
    """Samples whose verifier raised (scored as wrong)."""
    truncated: int
    """Samples cut at max_new_tokens."""
    weight_versions: set[int] = dataclasses.field(default_factory=set)
    """Weight versions stamped on the samples (a synced checkpoint's step; 0 for the plain model)."""


class Evaluator:
    def __init__(self, rollout, reward, tokenizer, system_prompt: str | None, max_batch_size: int,
                 progress: bool = True, few_shot=(), with_problems: bool = False):
        self.rollout, self.reward, self.tokenizer, self.few_shot = rollout, reward, tokenizer, few_shot
        self.with_problems = with_problems  # agent rollouts: the environments get each prompt's problem
        self.system_prompt, self.max_batch_size, self.progress = system_prompt, max_batch_size, progress

    def run(self, problems: list[Problem], passes: dict[str, SamplingParams]) -> dict[str, PassResult]:
        """Every pass over every problem; ``passes`` maps a name to its sampling parameters."""
        from tqdm import tqdm

        from infinirl.tasks.prompts import encode_prompts

        self._prompt_ids = encode_prompts(problems, self.tokenizer, self.system_prompt, few_shot=self.few_shot)
        self._problems = problems
        self._out = {name: PassResult(s.n, [[] for _ in problems], [[] for _ in problems], [[] for _ in problems],
                                      0, 0) for name, s in passes.items()}
        work = []
        for name, sampling in passes.items():
            per_call = max(1, self.max_batch_size // sampling.n)
            for start in range(0, len(problems), per_call):
                seed = None if sampling.seed is None else (sampling.seed * 1_000_003 + len(work)) % 2**31
                work.append((name, dataclasses.replace(sampling, seed=seed),
                             list(range(start, min(len(problems), start + per_call)))))
        total = sum(len(problems) * s.n for s in passes.values())
        with tqdm(total=total, desc="eval", unit="seq", disable=not self.progress) as self._bar:
            asyncio.run(self._drive(deque(work)))
        return self._out

    async def _drive(self, work: deque) -> None:
        scoring: list[asyncio.Future] = []

        async def rank_loop(rank: int) -> None:
            while work:
                name, sampling, indices = work.popleft()
                prompts = [self._prompt_ids[i] for i in indices]
                problems = [self._problems[i] for i in indices] if self.with_problems else None
                results = (await self.rollout.call("generate", prompts, sampling, problems, ranks=[rank]))[0]
                scoring.append(asyncio.ensure_future(self._score(name, indices, sampling.n, results, rank)))

        await asyncio.gather(*(rank_loop(r) for r in range(self.rollout.world_size)))
        await asyncio.gather(*scoring)

    async def _score(self, name: str, indices: list[int], n: int, results, rank: int) -> None:
        per_sample = [self._problems[i] for i in indices for _ in range(n)]
        scored = (await self.reward.call("score", results, per_sample, ranks=[rank % self.reward.world_size]))[0]
        out = self._out[name]
        keep_text = name == "greedy"
        texts = (self.tokenizer.batch_decode([r.response_ids for r in results], skip_special_tokens=True)
                 if keep_text else [])
        for j, (result, score) in enumerate(zip(results, scored)):
            i = indices[j // n]
            out.correct[i].append(bool(score.correct))
            if keep_text:
                out.responses[i].append(texts[j])
                out.logprobs[i].append(float(sum(result.response_logprobs)))
            out.errors += score.error is not None
            out.truncated += result.finish_reason == "length"
            out.weight_versions.add(int(result.weight_version))
        self._bar.update(len(results))


def summarize(passes: dict[str, PassResult], ks: list[int]) -> dict[str, float]:
    """``eval/greedy_accuracy``, ``eval/pass@1`` (mean correctness of the samples), ``eval/pass@k``."""
    metrics: dict[str, float] = {}
    if "greedy" in passes:
        greedy = passes["greedy"]
        correct = [c[0] for c in greedy.correct]
        metrics["eval/greedy_accuracy"] = float(np.mean(correct)) if correct else float("nan")
    if "sampled" in passes:
        sampled = passes["sampled"]
        counts = [sum(c) for c in sampled.correct]
        sizes = [len(c) for c in sampled.correct]
        metrics["eval/pass@1"] = float(np.mean([c / n for c, n in zip(counts, sizes)])) if counts else float("nan")
        for k in ks:
            metrics[f"eval/pass@{k}"] = mean_pass_at_k(sizes, counts, k)
    for name, result in passes.items():
        total = max(1, sum(len(c) for c in result.correct))
        metrics[f"eval/{name}_truncated_fraction"] = result.truncated / total
        metrics[f"eval/{name}_verifier_errors"] = float(result.errors)
    return metrics


def per_problem_records(problems: list[Problem], passes: dict[str, PassResult]) -> list[dict]:
    records = []
    for i, problem in enumerate(problems):
        record = {"uid": problem.uid, "answer": problem.answer}
        if "sampled" in passes:
            record["samples"] = len(passes["sampled"].correct[i])
            record["correct"] = int(sum(passes["sampled"].correct[i]))
        if "greedy" in passes:
            record["greedy_correct"] = passes["greedy"].correct[i][0]
            record["greedy_response"] = passes["greedy"].responses[i][0]
            record["greedy_logprob"] = passes["greedy"].logprobs[i][0]
        records.append(record)
    return records
