"""Soft Actor-Critic losses (Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications").

Pure functions over a replay mini-batch of ``B`` transitions; the caller owns the networks, the
target networks (Polyak averaging) and the optimizers. ``K`` critics (``K = 2``: clipped double-Q,
Fujimoto et al. 2018) are stacked on the first dim: ``q_values[k]`` is critic ``k``'s ``[B]``.
Actions may be single actions or whole chunks: the policy reports one joint log-prob per sample.

The temperature ``alpha`` is detached in the critic and actor losses: it is trained only by
:func:`sac_temperature_loss`. The losses are means over the batch (replay samples are i.i.d., so
the micro-batch-invariance machinery of ``aggregation`` is not needed here).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["SACLoss", "sac_actor_loss", "sac_critic_loss", "sac_temperature_loss", "soft_q_target"]


@dataclass(frozen=True)
class SACLoss:
    """A scalar loss and detached metrics."""

    loss: torch.Tensor
    metrics: dict[str, torch.Tensor] = field(default_factory=dict)


def _stacked(q_values: torch.Tensor, name: str) -> torch.Tensor:
    if isinstance(q_values, (list, tuple)):
        q_values = torch.stack(list(q_values))
    if q_values.dim() != 2:
        raise ValueError(f"{name} must be [K, B] (one row per critic), got {tuple(q_values.shape)}")
    return q_values


def _detached_alpha(alpha: float | torch.Tensor) -> torch.Tensor | float:
    return alpha.detach() if isinstance(alpha, torch.Tensor) else alpha


def soft_q_target(
    *,
    rewards: torch.Tensor,
    terminated: torch.Tensor,
    next_target_q_values: torch.Tensor,
    next_logprobs: torch.Tensor,
    alpha: float | torch.Tensor,
    gamma: float,
) -> torch.Tensor:
    """Soft Bellman target ``y = r + gamma * (1 - terminated) * (min_k Q'_k(s', a') - alpha *
    log pi(a'|s'))`` with ``a' ~ pi(.|s')`` and ``Q'`` the target critics (paper eq. 3, with the
    clipped double-Q min).

    Pass *terminations* only: a transition cut by a time limit must still bootstrap (Pardo et al.
    2018), so its flag is 0 here.
    """
    with torch.no_grad():
        next_q = _stacked(next_target_q_values, "next_target_q_values").min(dim=0).values
        soft_value = next_q - _detached_alpha(alpha) * next_logprobs
        continues = 1.0 - terminated.to(soft_value.dtype)
        return rewards.to(soft_value.dtype) + gamma * continues * soft_value


def sac_critic_loss(
    *,
    q_values: torch.Tensor,
    rewards: torch.Tensor,
    terminated: torch.Tensor,
    next_target_q_values: torch.Tensor,
    next_logprobs: torch.Tensor,
    alpha: float | torch.Tensor,
    gamma: float = 0.99,
) -> SACLoss:
    """``sum_k mean_B 0.5 * (Q_k(s, a) - y)^2`` with ``y`` = :func:`soft_q_target` (paper eq. 5;
    the 0.5 makes the gradient the TD error). Summing over critics trains each on one target."""
    q_values = _stacked(q_values, "q_values")
    target = soft_q_target(
        rewards=rewards, terminated=terminated, next_target_q_values=next_target_q_values,
        next_logprobs=next_logprobs, alpha=alpha, gamma=gamma,
    )
    td_errors = q_values - target[None]
    loss = (0.5 * td_errors**2).mean(dim=1).sum()
    metrics = {"q_mean": q_values.detach().mean(), "q_target_mean": target.mean(),
               "td_error_abs_mean": td_errors.detach().abs().mean()}
    return SACLoss(loss, metrics)


def sac_actor_loss(
    *, logprobs: torch.Tensor, q_values: torch.Tensor, alpha: float | torch.Tensor
) -> SACLoss:
    """``mean(alpha * log pi(a|s) - min_k Q_k(s, a))`` with ``a ~ pi(.|s)`` reparameterised, so the
    gradient flows through the action into the critics (paper eq. 7). Freeze the critics' parameters
    in the optimizer step, not here."""
    min_q = _stacked(q_values, "q_values").min(dim=0).values
    loss = (_detached_alpha(alpha) * logprobs - min_q).mean()
    return SACLoss(loss, {"policy_entropy": -logprobs.detach().mean()})


def sac_temperature_loss(
    *, log_alpha: torch.Tensor, logprobs: torch.Tensor, target_entropy: float
) -> SACLoss:
    """``mean(-log_alpha * (log pi(a|s) + target_entropy))`` (paper eq. 18, on ``log alpha`` so
    alpha stays positive): alpha rises when the policy's entropy falls below ``target_entropy``
    (commonly ``-action_dim``). ``logprobs`` are detached: only the temperature learns here."""
    loss = (-log_alpha * (logprobs.detach() + target_entropy)).mean()
    return SACLoss(loss, {"alpha": log_alpha.detach().exp()})
