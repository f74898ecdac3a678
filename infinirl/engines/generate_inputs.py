"""What every inference engine checks and defaults before it generates, the same way for all of
them: the prompts, the ids that end a response, and the stop ids of a request."""

from __future__ import annotations

import numbers
from collections.abc import Iterable, Sequence

from infinirl.engines.base import SamplingParams

__all__ = ["as_id_list", "default_eos_ids", "stop_token_ids", "validate_prompts"]


def validate_prompts(prompts: Sequence[Sequence[int]], sampling: SamplingParams, vocab_size: int,
                     max_length: int | None, max_length_name: str) -> None:
    """Refuse, naming the prompt and the fix, an empty prompt, one that is not token ids, an id
    outside ``[0, vocab_size)``, or a prompt whose length plus ``max_new_tokens`` exceeds
    ``max_length`` (``None``: no limit), which ``max_length_name`` names in the message."""
    for i, prompt in enumerate(prompts):
        if len(prompt) == 0:
            raise ValueError(f"generate: prompt {i} is empty; every prompt needs >= 1 token")
        if not all(isinstance(t, numbers.Integral) for t in prompt):
            raise TypeError(
                f"generate: prompt {i} must be a list of token ids (ints), got elements like "
                f"{next(t for t in prompt if not isinstance(t, numbers.Integral))!r}; "
                "tokenize first (apply_chat_template(..., return_dict=False))"
            )
        low, high = min(prompt), max(prompt)
        if low < 0 or high >= vocab_size:
            raise ValueError(
                f"generate: prompt {i} has token id {high if high >= vocab_size else low}"
                f" outside the model's vocabulary [0, {vocab_size})"
            )
        needed = len(prompt) + sampling.max_new_tokens
        if max_length is not None and needed > max_length:
            raise ValueError(
                f"generate: prompt {i} ({len(prompt)} tokens) + max_new_tokens="
                f"{sampling.max_new_tokens} = {needed} exceeds {max_length_name}={max_length}; "
                "shorten the prompt or lower max_new_tokens"
            )


def as_id_list(value) -> list[int]:
    """``None``, one id or several ids (a generation config's ``eos_token_id``) -> a list."""
    if value is None:
        return []
    if isinstance(value, numbers.Integral):
        return [int(value)]
    return [int(v) for v in value]


def default_eos_ids(explicit: Iterable[int] | None, generation_eos, tokenizer) -> tuple[int, ...]:
    """The ids that end a response: ``explicit`` when given, else the generation config's EOS ids
    (``generation_eos``: None, an id or a list) followed by the tokenizer's, without repeats."""
    if explicit is not None:
        return tuple(int(t) for t in explicit)
    ids = as_id_list(generation_eos) + as_id_list(getattr(tokenizer, "eos_token_id", None))
    return tuple(dict.fromkeys(ids))


def stop_token_ids(sampling: SamplingParams, eos_token_ids: Sequence[int]) -> list[int]:
    """The request's stop ids, then the engine's EOS ids unless ``ignore_eos``, in order, once each."""
    ids = list(sampling.stop_token_ids)
    if not sampling.ignore_eos:
        ids += eos_token_ids
    return list(dict.fromkeys(ids))
