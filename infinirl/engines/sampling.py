"""Choosing the next token: temperature, top-k / top-p filtering and sampling, with the log-prob of
the chosen token under InfiniRL's convention (``infinirl.engines.base``)."""

from __future__ import annotations

import torch

from infinirl.engines.base import SamplingParams

__all__ = ["NUCLEUS_SEARCH_WIDTH", "excluded_tokens", "outside_nucleus", "sample_from_weights", "sample_next_tokens"]

NUCLEUS_SEARCH_WIDTH = 64
"""Top-p looks for the nucleus among this many most likely tokens first: sorting the whole
vocabulary at every step costs far more than a top-k of a few dozen, and the nucleus usually holds
a handful of tokens. Rows whose nucleus is wider fall back to the full sort, so the result is exact
either way."""


def excluded_tokens(probs: torch.Tensor, top_k: int, top_p: float) -> torch.Tensor | None:
    """Mask of tokens that top-k, then top-p, exclude from sampling; None if both are off.

    ``probs [R, V]`` is the tempered, normalised distribution. As in HF and vLLM, top-p runs on
    the distribution renormalised over the top-k survivors.
    """
    vocab = probs.shape[-1]
    drop = None
    if 0 < top_k < vocab:
        kth_largest = torch.topk(probs, top_k, dim=-1).values[..., -1:]
        drop = probs < kth_largest  # ties with the k-th token are kept, as in HF
    if top_p < 1.0:
        if drop is not None:
            probs = probs.masked_fill(drop, 0.0)
            probs = probs / probs.sum(-1, keepdim=True)
        nucleus_drop = outside_nucleus(probs, top_p)
        drop = nucleus_drop if drop is None else drop | nucleus_drop
    return drop


def outside_nucleus(probs: torch.Tensor, top_p: float) -> torch.Tensor:
    """Tokens after the smallest most-likely prefix whose mass reaches ``top_p``."""

    def drop_from_sorted(sorted_probs, sorted_ids):
        mass_before = torch.cumsum(sorted_probs, dim=-1) - sorted_probs
        # A token is dropped once the more likely ones already reach top_p; the first never is.
        keep_sorted = mass_before < top_p
        keep = torch.zeros_like(probs[: len(sorted_ids)], dtype=torch.bool)
        return ~keep.scatter(-1, sorted_ids, keep_sorted)

    width = min(NUCLEUS_SEARCH_WIDTH, probs.shape[-1])
    top_probs, top_ids = torch.topk(probs, width, dim=-1)
    drop = drop_from_sorted(top_probs, top_ids)
    wide_rows = (top_probs.sum(-1) < top_p).nonzero().squeeze(-1)
    if wide_rows.numel():
        sorted_probs, sorted_ids = torch.sort(probs[wide_rows], dim=-1, descending=True)
        drop[wide_rows] = drop_from_sorted(sorted_probs, sorted_ids)
    return drop


def sample_from_weights(weights: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """One index per row of non-negative, not necessarily normalised ``weights [R, V]``.

    Inverse-CDF sampling: one cumsum and one binary search per row, where ``torch.multinomial``
    draws an exponential per vocabulary entry.
    """
    cdf = torch.cumsum(weights, dim=-1)
    u = torch.rand(
        (weights.shape[0], 1), generator=generator, device=weights.device, dtype=cdf.dtype
    )
    tokens = torch.searchsorted(cdf, u * cdf[:, -1:], right=True).squeeze(-1)
    # u * total can round up to the total itself: step back to the last token with weight.
    overflow = tokens >= weights.shape[-1]
    if overflow.any():
        last_positive = weights.shape[-1] - 1 - (weights.flip(-1) > 0).int().argmax(-1)
        tokens = torch.where(overflow, last_positive, tokens)
    return tokens


def sample_next_tokens(
    logits: torch.Tensor, sampling: SamplingParams, generator: torch.Generator | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick one token per row of float32 ``logits [R, V]``; return ``(tokens [R], logprobs [R])``.

    The log-prob is ``log softmax(logits / T)`` at the chosen token, over the full vocabulary
    (see ``infinirl.engines.base`` for why top-k/top-p are not renormalised into it).
    """
    temperature = sampling.logprob_temperature
    scaled = logits if temperature == 1.0 else logits / temperature
    logprobs = torch.log_softmax(scaled, dim=-1)
    if sampling.is_greedy:
        tokens = torch.argmax(logits, dim=-1)
    else:
        probs = logprobs.exp()
        drop = excluded_tokens(probs, sampling.top_k, sampling.top_p)
        if drop is not None:
            probs = probs.masked_fill(drop, 0.0)
        tokens = sample_from_weights(probs, generator)
    return tokens, logprobs.gather(-1, tokens.unsqueeze(-1)).squeeze(-1)
