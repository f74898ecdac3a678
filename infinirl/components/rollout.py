"""Rollout component: generates token ids + log-probs with versioned weights from the trainer."""

from __future__ import annotations

import time
from dataclasses import replace

import torch

from infinirl.engines.base import GenerationResult, SamplingParams
from infinirl.engines.seeds import chunk_seed
from infinirl.runtime import WeightSink, Worker


class RolloutWorker(Worker, WeightSink):
    """One rank of the inference engine. Rollout ranks are data-parallel over prompts."""

    def __init__(self, model: str, dtype: str = "float32", max_batch_size: int = 64, num_threads: int = 0,
                 engine: str = "hf", engine_options: dict | None = None, agent=None):
        from infinirl.engines.registry import build_rollout_engine

        if num_threads:
            torch.set_num_threads(num_threads)
        device = "cuda" if self.device == "cuda" else "cpu"
        self.engine = build_rollout_engine(engine, model, dtype, device, max_batch_size, engine_options)
        if hasattr(self.engine, "weight_refresh"):  # partial rollouts: staged weights load between decode steps
            self.engine.weight_refresh = self.apply_staged_weights
        self.agent = None if agent is None else self._agent_rollout(agent, model)

    def _agent_rollout(self, agent, model: str):
        """Multi-turn trajectories (``rollout.agent``): the engine generates each turn, the agent
        environment acts between turns (:mod:`infinirl.agents.loop`)."""
        from infinirl.agents.loop import AgentRollout
        from infinirl.agents.registered import load_agent_envs

        load_agent_envs()
        tokenizer = getattr(self.engine, "tokenizer", None)
        if tokenizer is None:
            from transformers import AutoTokenizer

            from infinirl.models.hf_causal_lm import resolve_model_source

            tokenizer = AutoTokenizer.from_pretrained(resolve_model_source(model))
        return AgentRollout(self.engine, tokenizer, agent.make_env_factory(), agent.budget())

    def _generate(self, prompt_ids: list[list[int]], sampling: SamplingParams, problems=None) -> list[GenerationResult]:
        if self.agent is not None:
            return self.agent.generate(prompt_ids, sampling, problems)
        return self.engine.generate(prompt_ids, sampling)

    def generate(self, prompt_ids: list[list[int]], sampling: SamplingParams,
                 problems: list | None = None) -> list[GenerationResult]:
        """``problems`` (agent rollouts only): the problem of each prompt, for the environments."""
        self.apply_staged_weights()
        return self._generate(prompt_ids, sampling, problems)

    def generate_to(self, channel, chunks: list[tuple[int, list[list[int]]]], sampling: SamplingParams,
                    key: str = "default", problems: list[list] | None = None) -> float:
        """Generate chunk after chunk and put each ``(index, results)`` into ``channel`` (under
        ``key``: one per generation, so several can be in flight) as soon as it is done, so the next
        stage (reward) works on chunk i while this rank generates chunk i+1.

        Each chunk is sampled with a seed derived from its *index*, not from this rank, so a batch's
        samples are the same however the chunks are spread over rollout ranks
        (:func:`~infinirl.engines.seeds.chunk_seed`; an agent's turns derive theirs from it). ``problems[c]`` (agent
        rollouts only) lists the problems of chunk ``c``'s prompts, for the agent environments.

        Returns the seconds this rank spent on the call: the producer's own generation time. The
        driver's wait for a batch is no measure of it when batches are generated ahead of the
        trainer (asynchronous runs), where that wait is near zero.
        """
        start = time.perf_counter()
        for position, (index, prompt_ids) in enumerate(chunks):
            self.apply_staged_weights()
            chunk_sampling = sampling if sampling.seed is None else replace(
                sampling, seed=chunk_seed(sampling.seed, index))
            results = self._generate(prompt_ids, chunk_sampling, None if problems is None else problems[position])
            channel.put((index, results), key=key, weight=len(results))
        channel.flush()
        return time.perf_counter() - start

    def load_weights(self, named_tensors, version: int, changed_only: bool = False) -> None:
        if changed_only:
            self.engine.load_weights(named_tensors, version, changed_only=True)
        else:
            self.engine.load_weights(named_tensors, version)

    def offload(self) -> None:
        self.engine.offload()

    def reload(self) -> None:
        self.engine.reload()
