"""Rollout component: generates token ids + log-probs with versioned weights from the trainer."""

from __future__ import annotations

from dataclasses import replace

import torch

from infinirl.engines.base import GenerationResult, SamplingParams
from infinirl.runtime import WeightSink, Worker


class RolloutWorker(Worker, WeightSink):
    """One rank of the inference engine. Rollout ranks are data-parallel over prompts."""

    def __init__(self, model: str, dtype: str = "float32", max_batch_size: int = 64, num_threads: int = 0,
                 engine: str = "hf", engine_options: dict | None = None):
        from infinirl.engines.registry import build_rollout_engine

        if num_threads:
            torch.set_num_threads(num_threads)
        device = "cuda" if self.device == "cuda" else "cpu"
        self.engine = build_rollout_engine(engine, model, dtype, device, max_batch_size, engine_options)
        if hasattr(self.engine, "weight_refresh"):  # partial rollouts: staged weights load between decode steps
            self.engine.weight_refresh = self.apply_staged_weights

    def generate(self, prompt_ids: list[list[int]], sampling: SamplingParams) -> list[GenerationResult]:
        self.apply_staged_weights()
        return self.engine.generate(prompt_ids, sampling)

    def generate_to(self, channel, chunks: list[tuple[int, list[list[int]]]], sampling: SamplingParams,
                    key: str = "default") -> int:
        """Generate chunk after chunk and put each ``(index, results)`` into ``channel`` (under
        ``key``: one per generation, so several can be in flight) as soon as it is done, so the next
        stage (reward) works on chunk i while this rank generates chunk i+1.

        Each chunk is sampled with a seed derived from its *index*, not from this rank, so a batch's
        samples are the same however the chunks are spread over rollout ranks.
        """
        for index, prompt_ids in chunks:
            self.apply_staged_weights()
            chunk_sampling = sampling if sampling.seed is None else replace(
                sampling, seed=(sampling.seed + 7919 * index) % (2**31))
            results = self.engine.generate(prompt_ids, chunk_sampling)
            channel.put((index, results), key=key, weight=len(results))
        channel.flush()
        return len(chunks)

    def load_weights(self, named_tensors, version: int) -> None:
        self.engine.load_weights(named_tensors, version)

    def offload(self) -> None:
        self.engine.offload()

    def reload(self) -> None:
        self.engine.reload()
