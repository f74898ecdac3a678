"""Per-token policy, value and entropy losses for on-policy (and slightly off-policy) RL.

Every function returns a per-token **loss matrix** shaped like its inputs (``[B, L]``; any
``[B, ...]`` works), 0 outside ``response_mask``, plus detached **metrics** (masked means over the
tensors it was given). A NaN or inf of any input at a masked position reaches neither the loss nor
its gradient (factors such as advantages and importance weights are zeroed there before they
multiply). It does not reduce: reduction is ``aggregation.aggregate`` with a
mini-batch-global normaliser, which is what keeps gradients independent of micro-batching. The
total objective is a sum of loss matrices, e.g.
``pg.loss_mat + kl_coef * kl_loss(...) + entropy_coef * entropy_loss(...)``, aggregated once.

Policy losses are registered in ``POLICY_LOSSES`` with one keyword-only signature::

    loss_fn(*, logprobs, old_logprobs, advantages, response_mask,
            behaviour_logprobs=None, is_cap=None, is_cap_mode="truncate", **hyperparameters)

Three log-probs of the same tokens may appear:

* ``logprobs``: current policy pi_theta (with gradient);
* ``old_logprobs``: the policy the trust region is centred on, recomputed by the trainer before the
  update (PPO's pi_old; AReaL's *proximal* policy);
* ``behaviour_logprobs``: the policy that actually sampled the tokens (the rollout engine). When it
  differs from ``old_logprobs`` (inference-engine numerics, or stale weights in async RL) the loss
  is reweighted per token by ``w = pi_old / pi_behaviour`` (detached):

  - truncated importance sampling, TIS (Yao et al. 2025, "Your Efficient RL Framework Secretly
    Brings You Off-Policy RL Training"): ``is_cap=C, is_cap_mode="truncate"`` -> ``min(w, C)``;
  - decoupled PPO (Fu et al. 2025, AReaL, eq. 5): ``behaviour_logprobs`` from the stale version,
    ``old_logprobs`` the proximal policy; ``is_cap_mode="mask"`` drops tokens with ``w > C``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from infinirl.algorithms.masking import masked_max, masked_mean, masked_min, zero_outside
from infinirl.algorithms.registry import POLICY_LOSSES

__all__ = [
    "LossOutput",
    "behaviour_importance_weight",
    "entropy_from_logits",
    "entropy_loss",
    "policy_gradient_loss",
    "ppo_clip_loss",
    "truncated_importance_weight",
    "value_loss",
]

# exp() of a log-ratio beyond this overflows float32/bf16 into inf; such tokens are clipped anyway.
_MAX_LOG_RATIO = 20.0


@dataclass(frozen=True)
class LossOutput:
    """A per-token loss matrix (0 where masked) and detached scalar metrics."""

    loss_mat: torch.Tensor
    metrics: dict[str, torch.Tensor] = field(default_factory=dict)


# --- importance weights between the behaviour (rollout) and the old/proximal policy ------------


def _importance_ratio(old_logprobs: torch.Tensor, behaviour_logprobs: torch.Tensor) -> torch.Tensor:
    log_ratio = (old_logprobs - behaviour_logprobs).detach()
    return torch.exp(log_ratio.clamp(max=_MAX_LOG_RATIO))


def _truncate_above_cap(weight: torch.Tensor, cap: float) -> torch.Tensor:
    return weight.clamp(max=cap)


def _mask_above_cap(weight: torch.Tensor, cap: float) -> torch.Tensor:
    return torch.where(weight > cap, torch.zeros_like(weight), weight)


_CAP_MODES: dict[str, Callable[[torch.Tensor, float], torch.Tensor]] = {
    "truncate": _truncate_above_cap,  # TIS: down-weight a far off-policy token
    # AReaL: drop it. It still counts in the aggregation normaliser, which is fixed beforehand.
    "mask": _mask_above_cap,
}


def truncated_importance_weight(
    old_logprobs: torch.Tensor, behaviour_logprobs: torch.Tensor, cap: float
) -> torch.Tensor:
    """TIS weight ``min(exp(old - behaviour), cap)``, detached: it corrects the sampling
    distribution, it is not something to optimise. Multiply it into any per-token loss."""
    return _truncate_above_cap(_importance_ratio(old_logprobs, behaviour_logprobs), cap)


def behaviour_importance_weight(
    old_logprobs: torch.Tensor,
    behaviour_logprobs: torch.Tensor,
    response_mask: torch.Tensor,
    *,
    cap: float | None = None,
    cap_mode: str = "truncate",
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Detached per-token ``pi_old / pi_behaviour``, capped per ``cap_mode``, and its metrics.

    The metrics include the rollout-vs-trainer log-prob mismatch DESIGN.md asks every run to log.
    """
    if cap_mode not in _CAP_MODES:
        raise ValueError(f"unknown is_cap_mode {cap_mode!r}; choose one of {sorted(_CAP_MODES)}")
    if cap is not None and cap <= 0:
        raise ValueError(f"is_cap must be positive, got {cap}")
    raw = _importance_ratio(old_logprobs, behaviour_logprobs)
    weight = raw if cap is None else _CAP_MODES[cap_mode](raw, cap)
    capped = raw > cap if cap is not None else torch.zeros_like(raw, dtype=torch.bool)
    metrics = {
        "is_weight_mean": masked_mean(weight, response_mask),
        "is_weight_max": masked_max(raw, response_mask),
        "is_capped_fraction": masked_mean(capped.to(raw.dtype), response_mask),
        "behaviour_logprob_abs_diff": masked_mean(
            (old_logprobs - behaviour_logprobs).detach().abs(), response_mask
        ),
    }
    return weight, metrics


# --- policy losses -----------------------------------------------------------------------------


def _ratio(logprobs: torch.Tensor, old_logprobs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    log_ratio = (logprobs - old_logprobs.detach()).clamp(-_MAX_LOG_RATIO, _MAX_LOG_RATIO)
    return torch.exp(log_ratio), log_ratio


def _ratio_metrics(ratio: torch.Tensor, log_ratio: torch.Tensor, mask: torch.Tensor) -> dict:
    ratio, log_ratio = ratio.detach(), log_ratio.detach()
    return {
        # k3 estimate of KL(pi_old || pi_theta) from tokens sampled by pi_old (Schulman 2020)
        "approx_kl": masked_mean((ratio - 1.0) - log_ratio, mask),
        "ratio_mean": masked_mean(ratio, mask),
        "ratio_max": masked_max(ratio, mask),
        "ratio_min": masked_min(ratio, mask),
    }


def _apply_behaviour_correction(
    loss: torch.Tensor,
    metrics: dict,
    old_logprobs: torch.Tensor,
    behaviour_logprobs: torch.Tensor | None,
    response_mask: torch.Tensor,
    is_cap: float | None,
    is_cap_mode: str,
) -> torch.Tensor:
    if behaviour_logprobs is None:
        if is_cap is not None:
            raise ValueError("is_cap needs behaviour_logprobs (the rollout engine's log-probs)")
        return loss
    weight, is_metrics = behaviour_importance_weight(
        old_logprobs, behaviour_logprobs, response_mask, cap=is_cap, cap_mode=is_cap_mode
    )
    metrics.update(is_metrics)
    return loss * _multiplier(weight, response_mask)


def _multiplier(factor: torch.Tensor, response_mask: torch.Tensor) -> torch.Tensor:
    """A per-token factor of the loss (an advantage, an importance weight), detached and 0 outside
    ``response_mask``. The final ``zero_outside`` drops a masked entry's value, but a NaN factor
    there would still reach the gradient as ``0 * NaN``."""
    return zero_outside(factor.detach(), response_mask)


def _check_shapes(**tensors: torch.Tensor) -> None:
    shapes = {name: tuple(t.shape) for name, t in tensors.items() if t is not None}
    if len(set(shapes.values())) > 1:
        raise ValueError(f"per-token inputs must share one shape; got {shapes}")


@POLICY_LOSSES.register("ppo_clip")
def ppo_clip_loss(
    *,
    logprobs: torch.Tensor,
    old_logprobs: torch.Tensor,
    advantages: torch.Tensor,
    response_mask: torch.Tensor,
    clip_low: float = 0.2,
    clip_high: float | None = None,
    clip_c: float | None = None,
    behaviour_logprobs: torch.Tensor | None = None,
    is_cap: float | None = None,
    is_cap_mode: str = "truncate",
) -> LossOutput:
    """PPO clipped surrogate per token: ``max(-A r, -A clip(r, 1 - clip_low, 1 + clip_high))``
    with ``r = pi_theta / pi_old`` (Schulman et al. 2017, eq. 7, negated to a loss).

    * ``clip_high`` (default ``clip_low``) > ``clip_low`` is DAPO's clip-higher (Yu et al. 2025,
      eq. 10): more room to raise unlikely tokens' probability, against entropy collapse.
    * ``clip_c`` (> 1) is dual-clip PPO (Ye et al. 2020, "Mastering Complex Control in MOBA Games",
      eq. 5): for ``A < 0`` the loss is further bounded by ``-clip_c * A``, so one token with a huge
      ratio cannot dominate the update.
    * ``behaviour_logprobs`` / ``is_cap`` / ``is_cap_mode``: TIS or decoupled PPO (module doc).
    """
    _check_shapes(
        logprobs=logprobs, old_logprobs=old_logprobs, advantages=advantages,
        response_mask=response_mask, behaviour_logprobs=behaviour_logprobs,
    )
    clip_high = clip_low if clip_high is None else clip_high
    if not 0.0 <= clip_low < 1.0 or clip_high < 0.0:
        raise ValueError(f"need 0 <= clip_low < 1 and clip_high >= 0; got {clip_low}, {clip_high}")
    if clip_c is not None and clip_c <= 1.0:
        raise ValueError(f"dual-clip constant clip_c must be > 1, got {clip_c}")
    advantages = _multiplier(advantages, response_mask)
    ratio, log_ratio = _ratio(logprobs, old_logprobs)
    unclipped = -advantages * ratio
    clipped = -advantages * ratio.clamp(1.0 - clip_low, 1.0 + clip_high)
    loss = torch.maximum(unclipped, clipped)
    metrics = _ratio_metrics(ratio, log_ratio, response_mask)
    metrics["clip_fraction"] = masked_mean((clipped > unclipped).to(ratio.dtype), response_mask)
    if clip_c is not None:
        bound = -advantages * clip_c
        dual_active = (advantages < 0) & (bound < loss)
        loss = torch.where(dual_active, bound, loss)
        metrics["dual_clip_fraction"] = masked_mean(dual_active.to(ratio.dtype), response_mask)
    loss = _apply_behaviour_correction(
        loss, metrics, old_logprobs, behaviour_logprobs, response_mask, is_cap, is_cap_mode
    )
    return LossOutput(zero_outside(loss, response_mask), _detached(metrics))


@POLICY_LOSSES.register("policy_gradient")
def policy_gradient_loss(
    *,
    logprobs: torch.Tensor,
    old_logprobs: torch.Tensor,
    advantages: torch.Tensor,
    response_mask: torch.Tensor,
    behaviour_logprobs: torch.Tensor | None = None,
    is_cap: float | None = None,
    is_cap_mode: str = "truncate",
) -> LossOutput:
    """Unclipped importance-weighted policy gradient ``-A * pi_theta / pi_old`` per token. On-policy
    (``pi_theta == pi_old``) its gradient is REINFORCE's ``-A * grad log pi`` (Williams 1992); use
    it with one update per batch, where PPO's clipping never triggers anyway."""
    _check_shapes(
        logprobs=logprobs, old_logprobs=old_logprobs, advantages=advantages,
        response_mask=response_mask, behaviour_logprobs=behaviour_logprobs,
    )
    ratio, log_ratio = _ratio(logprobs, old_logprobs)
    loss = -_multiplier(advantages, response_mask) * ratio
    metrics = _ratio_metrics(ratio, log_ratio, response_mask)
    loss = _apply_behaviour_correction(
        loss, metrics, old_logprobs, behaviour_logprobs, response_mask, is_cap, is_cap_mode
    )
    return LossOutput(zero_outside(loss, response_mask), _detached(metrics))


def _detached(metrics: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {name: value.detach() for name, value in metrics.items()}


# --- entropy -----------------------------------------------------------------------------------


def entropy_from_logits(logits: torch.Tensor) -> torch.Tensor:
    """Entropy of ``softmax(logits)`` over the last dim: ``logsumexp(z) - sum(softmax(z) * z)``,
    stable for large logits (no ``log(softmax)`` of underflowed probabilities)."""
    probs = torch.softmax(logits, dim=-1)
    return torch.logsumexp(logits, dim=-1) - (probs * logits).sum(dim=-1)


def entropy_loss(
    response_mask: torch.Tensor,
    *,
    entropy: torch.Tensor | None = None,
    logits: torch.Tensor | None = None,
) -> LossOutput:
    """Entropy bonus as a loss matrix ``-H`` (add ``entropy_coef * loss_mat`` to the objective to
    reward exploration). Pass per-token ``entropy`` ([B, L]) or aligned ``logits`` ([B, L, V])."""
    if (entropy is None) == (logits is None):
        raise ValueError("entropy_loss needs exactly one of entropy= or logits=")
    if entropy is None:
        entropy = entropy_from_logits(logits)
    _check_shapes(entropy=entropy, response_mask=response_mask)
    metrics = {"entropy": masked_mean(entropy, response_mask)}
    return LossOutput(zero_outside(-entropy, response_mask), _detached(metrics))


# --- critic ------------------------------------------------------------------------------------


def value_loss(
    *,
    values: torch.Tensor,
    old_values: torch.Tensor,
    returns: torch.Tensor,
    response_mask: torch.Tensor,
    clip_range: float | None = None,
) -> LossOutput:
    """Critic loss ``0.5 * max((V - R)^2, (V_clip - R)^2)``, ``V_clip = V_old + clip(V - V_old,
    -clip_range, clip_range)`` (PPO value clipping as in OpenAI baselines' ppo2).

    The 0.5 makes the gradient ``(V - R)``: the plain regression error, so ``value_coef`` reads as
    a learning-rate ratio. Taking the max (not the min) makes clipping pessimistic: the update only
    gets smaller. Without ``clip_range`` it is ``0.5 * (V - R)^2``.
    """
    _check_shapes(
        values=values, old_values=old_values, returns=returns, response_mask=response_mask
    )
    # 0 outside the mask (where() passes no gradient there): a NaN at a masked position of any of
    # them would otherwise reach the gradient as 0 * NaN through the square.
    values = zero_outside(values, response_mask)
    returns, old_values = _multiplier(returns, response_mask), _multiplier(old_values, response_mask)
    unclipped = (values - returns) ** 2
    if clip_range is None:
        squared, clip_fraction = unclipped, torch.zeros_like(unclipped)
    else:
        clipped_values = old_values + (values - old_values).clamp(-clip_range, clip_range)
        clipped = (clipped_values - returns) ** 2
        squared = torch.maximum(unclipped, clipped)
        clip_fraction = (clipped > unclipped).to(values.dtype)
    metrics = {
        "value_clip_fraction": masked_mean(clip_fraction, response_mask),
        "value_mean": masked_mean(values, response_mask),
        "value_mse": masked_mean(unclipped, response_mask),
    }
    return LossOutput(zero_outside(0.5 * squared, response_mask), _detached(metrics))
