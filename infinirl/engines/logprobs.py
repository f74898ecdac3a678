"""Token log-probs and entropies from logits, without a float32 ``[B, L, V]`` for the whole batch.

A causal LM's logits at position ``t`` predict token ``t + 1``. The batch layout
(:mod:`infinirl.data.batch`) wants everything aligned with ``input_ids``, so the shift happens here,
once: ``logprobs[:, t] = log softmax(logits[:, t - 1] / T)[input_ids[:, t]]`` and position 0 (no
context) is 0.

Memory: the vocabulary is large (32k..256k) and logits often come in bf16. Upcasting all of them
to float32 for ``log_softmax`` doubles the largest tensor of the step. Instead we walk over chunks
of tokens: upcast a ``[chunk, V]`` block, take its ``logsumexp``, gather the target logit, and keep
only ``[chunk]`` results. With grad enabled each chunk is checkpointed, so backward recomputes the
float32 block instead of every chunk's block staying alive until backward.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint


def _chunk_logprobs(
    logits: torch.Tensor, targets: torch.Tensor, temperature: float, with_entropy: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """``[n, V]`` logits, ``[n]`` targets -> float32 ``[n]`` log-probs and entropies (or empty)."""
    scaled = logits.float()
    if temperature != 1.0:
        scaled = scaled / temperature
    log_norm = torch.logsumexp(scaled, dim=-1)
    logprobs = scaled.gather(-1, targets.unsqueeze(-1)).squeeze(-1) - log_norm
    if not with_entropy:
        return logprobs, logprobs.new_empty(0)
    # H = -sum p log p = logsumexp(x) - sum p x, which needs no second [n, V] log-prob tensor.
    probs = torch.softmax(scaled, dim=-1)
    entropy = log_norm - (probs * scaled).sum(-1)
    return logprobs, entropy


def token_logprobs(
    logits: torch.Tensor,
    targets: torch.Tensor,
    temperature: float = 1.0,
    chunk_tokens: int = 1024,
    with_entropy: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Log-prob of ``targets[i]`` under ``softmax(logits[i] / temperature)``; logits ``[..., V]``.

    Returns float32 tensors shaped like ``targets``; the entropy is ``None`` unless requested.
    """
    if temperature <= 0:
        raise ValueError(f"token_logprobs: temperature must be > 0, got {temperature}")
    if logits.shape[:-1] != targets.shape:
        raise ValueError(
            f"token_logprobs: logits {tuple(logits.shape)} do not match "
            f"targets {tuple(targets.shape)}"
        )
    vocab = logits.shape[-1]
    flat_logits = logits.reshape(-1, vocab)  # a view for contiguous logits: no copy
    flat_targets = targets.reshape(-1)
    use_checkpoint = torch.is_grad_enabled() and logits.requires_grad
    logprob_chunks, entropy_chunks = [], []
    for start in range(0, flat_targets.numel(), chunk_tokens):
        end = start + chunk_tokens
        args = (flat_logits[start:end], flat_targets[start:end], temperature, with_entropy)
        if use_checkpoint:
            lp, ent = checkpoint(_chunk_logprobs, *args, use_reentrant=False)
        else:
            lp, ent = _chunk_logprobs(*args)
        logprob_chunks.append(lp)
        entropy_chunks.append(ent)
    if not logprob_chunks:  # zero tokens
        empty = logits.new_zeros(targets.shape, dtype=torch.float32)
        return empty, (empty.clone() if with_entropy else None)
    logprobs = torch.cat(logprob_chunks).view(targets.shape)
    entropy = torch.cat(entropy_chunks).view(targets.shape) if with_entropy else None
    return logprobs, entropy


def aligned_logprobs(
    logits: torch.Tensor,
    input_ids: torch.Tensor,
    attention_mask: torch.Tensor | None = None,
    temperature: float = 1.0,
    chunk_tokens: int = 1024,
    with_entropy: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``[B, L, V]`` logits of ``[B, L]`` ids -> aligned ``[B, L]`` log-probs (and entropies).

    ``out[:, t]`` scores ``input_ids[:, t]`` given ``input_ids[:, :t]``; ``out[:, 0]`` and padded
    positions (``attention_mask == 0``) are 0. The entropy at ``t`` is that of the distribution
    that produced token ``t``.
    """
    if logits.shape[:2] != input_ids.shape:
        raise ValueError(
            f"aligned_logprobs: logits {tuple(logits.shape)} do not match "
            f"input_ids {tuple(input_ids.shape)}"
        )
    # Score every position against the *next* id. Using the full (contiguous) logits and a dummy
    # target for the last position avoids copying logits[:, :-1] into a new tensor.
    next_ids = torch.roll(input_ids, shifts=-1, dims=1)
    shifted_lp, shifted_ent = token_logprobs(
        logits, next_ids, temperature, chunk_tokens, with_entropy
    )
    logprobs = _shift_right(shifted_lp)
    entropy = _shift_right(shifted_ent) if shifted_ent is not None else None
    if attention_mask is not None:
        keep = attention_mask.to(torch.bool)
        logprobs = logprobs.masked_fill(~keep, 0.0)
        if entropy is not None:
            entropy = entropy.masked_fill(~keep, 0.0)
    return logprobs, entropy


def aligned_values(
    values: torch.Tensor, attention_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Per-position value-head outputs ``[B, L]`` -> aligned float32 ``[B, L]`` values.

    The head at position ``t - 1`` has read ``input_ids[:, :t]``: the state in which token ``t`` is
    chosen, whose value GAE pairs with token ``t``. So ``out[:, t] = values[:, t - 1]``, the same
    shift as :func:`aligned_logprobs`; ``out[:, 0]`` and padded positions are 0.
    """
    if values.dim() != 2:
        raise ValueError(f"aligned_values: expected [B, L] values, got {tuple(values.shape)}")
    out = _shift_right(values.float())
    if attention_mask is not None:
        out = out.masked_fill(~attention_mask.to(torch.bool), 0.0)
    return out


def _shift_right(scores: torch.Tensor) -> torch.Tensor:
    """Move scores of token ``t + 1`` from column ``t`` to column ``t + 1``; column 0 becomes 0."""
    return torch.cat([scores.new_zeros(scores.shape[0], 1), scores[:, :-1]], dim=1)
