"""Masked reductions over the aligned token layout (see ``infinirl/data/batch.py``).

Every per-token tensor is ``[B, L]`` and most entries are not trainable (prompt tokens, padding), so
every statistic here takes the mask that says which entries count. Masks may be bool, int or float
0/1; they are converted to the value dtype so float64 tests stay float64 end to end.
"""

from __future__ import annotations

import torch

__all__ = [
    "explained_variance",
    "last_valid_index",
    "masked_max",
    "masked_mean",
    "masked_min",
    "masked_whiten",
    "reverse_discounted_scan",
    "zero_outside",
]


def as_weight(mask: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``mask`` as 0/1 values of ``like``'s dtype and device, checked to have ``like``'s shape."""
    if mask.shape != like.shape:
        raise ValueError(f"mask shape {tuple(mask.shape)} differs from values {tuple(like.shape)}")
    return mask.to(dtype=like.dtype, device=like.device)


def zero_outside(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``values * mask`` that stays finite where masked-out entries are inf/NaN (a ratio or a
    log-prob on a padding token): ``where`` drops them from both the value and the gradient."""
    weight = as_weight(mask, values)
    return torch.where(weight != 0, values * weight, torch.zeros_like(values))


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` where ``mask`` is 1; 0 when nothing is valid (an empty micro-batch must
    not turn metrics into NaN)."""
    return zero_outside(values, mask).sum() / as_weight(mask, values).sum().clamp(min=1.0)


def masked_max(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Max of ``values`` where ``mask`` is 1; 0 when nothing is valid. Branch- and index-free (no
    device sync, no ``nonzero``): masked-out entries become ``-inf`` before the reduction."""
    return _masked_extreme(values, mask, torch.amax, float("-inf"))


def masked_min(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Min of ``values`` where ``mask`` is 1; 0 when nothing is valid (see :func:`masked_max`)."""
    return _masked_extreme(values, mask, torch.amin, float("inf"))


def _masked_extreme(values: torch.Tensor, mask: torch.Tensor, reduce, neutral: float) -> torch.Tensor:
    valid = as_weight(mask, values) != 0
    extreme = reduce(torch.where(valid, values, torch.full_like(values, neutral)))
    return torch.where(valid.any(), extreme, torch.zeros_like(extreme))


def masked_whiten(values: torch.Tensor, mask: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """``(x - mean) / sqrt(var + eps)`` over the valid entries of the whole tensor; others 0.

    The variance is the population variance (divide by the count), as in OpenRLHF's REINFORCE++
    whitening; with thousands of tokens the Bessel correction is irrelevant and this keeps a single
    valid entry finite (it whitens to 0).
    """
    mean = masked_mean(values, mask)
    var = masked_mean((values - mean) ** 2, mask)
    return zero_outside((values - mean) * torch.rsqrt(var + eps), mask)


def explained_variance(values: torch.Tensor, returns: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``1 - Var(returns - values) / Var(returns)`` over the valid entries: how much of the return's
    variance the critic explains (1 perfect, 0 no better than a constant, < 0 worse than one).

    Population variances over all valid tokens of the batch; 0 (not NaN) when the returns do not
    vary, as there is nothing to explain.
    """
    var_returns = masked_mean((returns - masked_mean(returns, mask)) ** 2, mask)
    residual = returns - values
    var_residual = masked_mean((residual - masked_mean(residual, mask)) ** 2, mask)
    if var_returns <= 0:
        return var_returns.new_zeros(())
    return 1.0 - var_residual / var_returns


def last_valid_index(mask: torch.Tensor) -> torch.Tensor:
    """Per row of a ``[B, L]`` mask, the column of its last 1, or -1 for an all-zero row.

    That is where a sequence-level reward lands: on the last generated token.
    """
    if mask.dim() != 2:
        raise ValueError(f"expected a [B, L] mask, got shape {tuple(mask.shape)}")
    valid = mask.bool()
    columns = torch.arange(mask.shape[1], device=mask.device).expand_as(valid)
    return torch.where(valid, columns, torch.full_like(columns, -1)).amax(dim=1)


def reverse_discounted_scan(
    rewards: torch.Tensor,
    values: torch.Tensor,
    mask: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """GAE over the valid tokens of each row of ``[B, L]`` tensors, scanning right to left.

    ``delta_t = r_t + gamma * V(next valid) - V_t`` and ``A_t = delta_t + gamma * lam * A(next
    valid)`` (Schulman et al. 2016, "High-Dimensional Continuous Control Using GAE", eq. 16), with
    ``V = A = 0`` after the last valid token (the response ends the episode). Masked positions are
    *transparent*: they get advantage 0 and the chain links each valid token to the next valid one,
    so prompt tokens, padding and (in multi-turn rollouts) tool-output tokens between two generated
    spans are skipped rather than treated as steps. With ``values = 0`` and ``lam = 1`` the result
    is the discounted reward-to-go.
    """
    weight = as_weight(mask, rewards)
    valid = weight.bool()
    advantages = torch.zeros_like(rewards)
    next_value = rewards.new_zeros(rewards.shape[0])
    next_advantage = rewards.new_zeros(rewards.shape[0])
    for t in range(rewards.shape[1] - 1, -1, -1):
        delta = rewards[:, t] + gamma * next_value - values[:, t]
        advantage = delta + gamma * lam * next_advantage
        next_advantage = torch.where(valid[:, t], advantage, next_advantage)
        next_value = torch.where(valid[:, t], values[:, t], next_value)
        advantages[:, t] = advantage * weight[:, t]
    return advantages
