"""Requests to vLLM and results from it: InfiniRL's sampling settings as vLLM's, per-prompt seeds,
and vLLM's completions as :class:`~infinirl.engines.base.GenerationResult`."""

from __future__ import annotations

import hashlib
from collections.abc import Collection

from infinirl.engines.base import GenerationResult, SamplingParams

__all__ = ["VLLM_MIN_TEMPERATURE", "prompt_seed", "to_generation_result", "vllm_sampling_params"]

VLLM_MIN_TEMPERATURE = 0.01
"""vLLM's ``SamplingParams`` raises a temperature in ``(0, 0.01)`` to 0.01 (with a warning), so its
samples and log-probs would follow 0.01 while the trainer scores at the configured temperature."""


def vllm_sampling_params(sampling: SamplingParams, n: int, stop_ids: list[int], seed: int | None):
    """vLLM's ``SamplingParams`` for ``sampling``, ``n`` samples a request, ending at ``stop_ids``."""
    greedy = sampling.is_greedy
    if not greedy and sampling.temperature < VLLM_MIN_TEMPERATURE:
        raise ValueError(
            f"VLLMEngine: temperature={sampling.temperature} is below vLLM's floor of {VLLM_MIN_TEMPERATURE}, "
            "to which vLLM would raise it (the log-probs would then not be the requested temperature's); "
            f"use a temperature >= {VLLM_MIN_TEMPERATURE}, 0 for greedy, or the hf engine"
        )
    from vllm import SamplingParams as VLLMSamplingParams

    return VLLMSamplingParams(
        n=n,
        temperature=0.0 if greedy else sampling.temperature,
        top_p=1.0 if greedy else sampling.top_p,
        top_k=0 if greedy else sampling.top_k,
        max_tokens=sampling.max_new_tokens,
        seed=seed,
        # EOS is handled as an ordinary stop id, so `eos_token_ids` decides what ends a
        # response (vLLM would otherwise add the model's own EOS ids on its own).
        ignore_eos=True,
        stop_token_ids=stop_ids,
        stop=list(sampling.stop_strings) or None,
        include_stop_str_in_output=True,
        # Stop strings are matched on the text of *all* tokens, like HFGenerateEngine's.
        skip_special_tokens=False,
        spaces_between_special_tokens=False,
        detokenize=bool(sampling.stop_strings),  # text is never returned: decode only to stop
        logprobs=0,  # the sampled token's log-prob only
    )


def to_generation_result(prompt, prompt_index: int, sample_index: int, completion, weight_version: int,
                         stop_ids: Collection[int] = ()) -> GenerationResult:
    """One vLLM completion as a :class:`GenerationResult`, refusing one without per-token log-probs.
    ``stop_ids``: the ids that ended responses of this request (a response whose last id is one of
    them finished with ``"stop"``, whatever vLLM reports)."""
    response = list(completion.token_ids)
    if completion.logprobs is None or len(completion.logprobs) != len(response):
        raise RuntimeError(
            "VLLMEngine: vLLM returned no per-token log-probs for a response "
            f"({0 if completion.logprobs is None else len(completion.logprobs)} for "
            f"{len(response)} tokens)"
        )
    logprobs = [float(step[token].logprob) for step, token in zip(completion.logprobs, response)]
    finish_reason = completion.finish_reason
    if finish_reason not in ("stop", "length"):
        raise RuntimeError(
            f"VLLMEngine: request finished with {finish_reason!r} "
            f"(stop_reason={completion.stop_reason!r}); expected 'stop' or 'length'"
        )
    if finish_reason == "length" and response and response[-1] in stop_ids:
        # Older vLLM V1 checks the token cap before the stop ids, so a stop id sampled as the last
        # allowed token is reported as "length"; it ended the response all the same (as the HF
        # engine reports it), and the trainer's truncation handling must not take it for a cut.
        finish_reason = "stop"
    extra = {}
    if isinstance(completion.stop_reason, str):
        extra["stop_string"] = completion.stop_reason
    return GenerationResult(
        prompt_ids=list(prompt),
        response_ids=response,
        response_logprobs=logprobs,
        finish_reason=finish_reason,
        weight_version=weight_version,
        prompt_index=prompt_index,
        sample_index=sample_index,
        extra=extra,
    )


def prompt_seed(seed: int, prompt_index: int) -> int:
    """A per-prompt seed: vLLM seeds sample k of a request with ``seed + k``, so prompts sharing
    one seed would draw identical samples. Hashing keeps prompts apart and the result independent
    of batching."""
    digest = hashlib.blake2b(f"{seed}/{prompt_index}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & (2**62 - 1)
