"""Requests to vLLM and results from it: InfiniRL's sampling settings as vLLM's, per-prompt seeds,
and vLLM's completions as :class:`~infinirl.engines.base.GenerationResult`."""

from __future__ import annotations

import hashlib

from infinirl.engines.base import GenerationResult, SamplingParams

__all__ = ["prompt_seed", "to_generation_result", "vllm_sampling_params"]


def vllm_sampling_params(sampling: SamplingParams, n: int, stop_ids: list[int], seed: int | None):
    """vLLM's ``SamplingParams`` for ``sampling``, ``n`` samples a request, ending at ``stop_ids``."""
    from vllm import SamplingParams as VLLMSamplingParams

    greedy = sampling.is_greedy
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


def to_generation_result(prompt, prompt_index: int, sample_index: int, completion,
                         weight_version: int) -> GenerationResult:
    """One vLLM completion as a :class:`GenerationResult`, refusing one without per-token log-probs."""
    response = list(completion.token_ids)
    if completion.logprobs is None or len(completion.logprobs) != len(response):
        raise RuntimeError(
            "VLLMEngine: vLLM returned no per-token log-probs for a response "
            f"({0 if completion.logprobs is None else len(completion.logprobs)} for "
            f"{len(response)} tokens)"
        )
    logprobs = [float(step[token].logprob) for step, token in zip(completion.logprobs, response)]
    if completion.finish_reason not in ("stop", "length"):
        raise RuntimeError(
            f"VLLMEngine: request finished with {completion.finish_reason!r} "
            f"(stop_reason={completion.stop_reason!r}); expected 'stop' or 'length'"
        )
    extra = {}
    if isinstance(completion.stop_reason, str):
        extra["stop_string"] = completion.stop_reason
    return GenerationResult(
        prompt_ids=list(prompt),
        response_ids=response,
        response_logprobs=logprobs,
        finish_reason=completion.finish_reason,
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
