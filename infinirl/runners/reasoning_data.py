"""The reasoning runner's problems (through the task-source registry, :mod:`infinirl.tasks.sources`)
and the prompt-length check every prompt passes before it is generated from."""

from __future__ import annotations

from collections.abc import Sequence

from transformers import AutoTokenizer

from infinirl.config import ConfigError
from infinirl.models.hf_causal_lm import resolve_model_source
from infinirl.tasks.sources import training_problems


def build_problem_sources(cfg):
    """``(train stream, held-out problems, tokenizer)`` of the run's task, read in the driver."""
    train, eval_problems = training_problems(cfg.task, cfg.seed)
    tokenizer = AutoTokenizer.from_pretrained(resolve_model_source(cfg.model.path))
    if tokenizer.pad_token_id is None:
        tokenizer.pad_token = tokenizer.eos_token
    return train, eval_problems, tokenizer


class PromptTooLongError(ConfigError):
    """A training or eval prompt is longer than ``rollout.max_prompt_length``."""


def encode_checked(problems, tokenizer, system_prompt: str | None, max_prompt_length: int,
                   split: str, few_shot=()) -> list[list[int]]:
    """Prompt ids of ``problems``, refusing any longer than ``max_prompt_length`` tokens."""
    from infinirl.tasks.prompts import encode_prompts

    prompt_ids = encode_prompts(problems, tokenizer, system_prompt, few_shot=few_shot)
    check_prompt_lengths(prompt_ids, problems, max_prompt_length, split)
    return prompt_ids


def check_prompt_lengths(prompt_ids: Sequence[Sequence[int]], problems, max_prompt_length: int,
                         split: str) -> None:
    """Raise :class:`PromptTooLongError` naming the first over-long prompt, its length and the fix."""
    for ids, problem in zip(prompt_ids, problems):
        if len(ids) > max_prompt_length:
            longest = max(len(p) for p in prompt_ids)
            text = problem.prompt if len(problem.prompt) <= 80 else problem.prompt[:77] + "..."
            raise PromptTooLongError(
                f"rollout.max_prompt_length={max_prompt_length}: {split} prompt {problem.uid!r} is {len(ids)} "
                f"tokens long (chat template and system prompt included; the longest of its batch is {longest}): "
                f"{text!r}. "
                f"Raise rollout.max_prompt_length to at least {longest} (prompt plus rollout.max_new_tokens must "
                "fit the model's context), shorten task.system_prompt, or remove such problems from the data."
            )
