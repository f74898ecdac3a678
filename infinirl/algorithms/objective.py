"""The actor's per-micro-batch objective: policy loss + KL + entropy, one global normaliser.

Every term is aggregated with the same mode and the same mini-batch-global normaliser, so the
gradient of a mini-batch does not depend on how it is split into micro-batches or ranks (see
``aggregation``). When ``old_logprobs`` are absent the batch is on-policy for a single update and
the current log-probs (detached) serve as the old ones: that saves a whole forward pass per step.

Off-policy correction (asynchronous training, or rollout-engine numerics): ``is_cap`` reweights
every token by ``w = pi_old / pi_behaviour`` (the rollout engine's log-probs), capped. ``pi_old``
is the *proximal* policy: the trainer's weights at the start of the step, so PPO's trust region is
centred on them and ``w`` corrects for the version (or engine) that actually sampled the token
(decoupled PPO, Fu et al. 2025). ``is_cap_mode=truncate`` is TIS (``min(w, cap)``),
``mask`` is MIS / AReaL's choice (tokens with ``w > cap`` are dropped).

``train/logprob_mismatch_mean`` / ``_max`` (when the batch carries the rollout's log-probs): the
gap between the trainer's log-probs before the update (the old ones above) and the rollout's, per
token: the engines' numerics, plus the version gap in asynchronous training; not the policy's own
drift over the update's mini-batches.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from infinirl.algorithms.aggregation import aggregate
from infinirl.algorithms.kl import kl_loss
from infinirl.algorithms.losses import entropy_loss, ppo_clip_loss
from infinirl.algorithms.masking import masked_max, masked_mean


@dataclass
class PolicyObjectiveConfig:
    """Hyperparameters of the policy objective (every field is a config key under `algorithm.`)."""

    clip_low: float = 0.2
    """PPO ratio clip below 1."""
    clip_high: float = 0.2
    """PPO ratio clip above 1; > clip_low is DAPO's clip-higher."""
    clip_c: float | None = None
    """Dual-clip bound for negative advantages (> 1), or None."""
    aggregation: str = "token-mean"
    """token-mean | seq-mean-token-sum | seq-mean-token-mean | seq-mean-token-sum-norm."""
    kl_coef: float = 0.0
    """Weight of the KL-to-reference loss term (needs a reference policy); 0 disables it."""
    kl_estimator: str = "k3"
    entropy_coef: float = 0.0
    """Entropy bonus weight (adds -coef * H)."""
    is_cap: float | None = None
    """Cap on the per-token importance weight pi_old / pi_rollout (behaviour-policy correction:
    stale weights in asynchronous training, engine numerics); None applies no correction."""
    is_cap_mode: Literal["truncate", "mask"] = "truncate"
    """truncate: TIS, min(w, is_cap). mask: MIS (AReaL's decoupled PPO), tokens with w > is_cap
    get no gradient."""


def policy_objective(micro_batch, logprobs: torch.Tensor, entropy: torch.Tensor | None,
                     cfg: PolicyObjectiveConfig, normaliser: float) -> tuple[torch.Tensor, dict]:
    mask = micro_batch["response_mask"]
    old = micro_batch["old_logprobs"] if "old_logprobs" in micro_batch.keys() else logprobs.detach()
    behaviour = micro_batch["rollout_logprobs"] if cfg.is_cap is not None else None
    out = ppo_clip_loss(
        logprobs=logprobs, old_logprobs=old, advantages=micro_batch["advantages"], response_mask=mask,
        clip_low=cfg.clip_low, clip_high=cfg.clip_high, clip_c=cfg.clip_c,
        behaviour_logprobs=behaviour, is_cap=cfg.is_cap, is_cap_mode=cfg.is_cap_mode,
    )
    loss = aggregate(out.loss_mat, mask, cfg.aggregation, normaliser)
    metrics = {f"train/{k}": float(v) for k, v in out.metrics.items()}
    if cfg.kl_coef > 0:
        kl = kl_loss(logprobs, micro_batch["ref_logprobs"], mask, cfg.kl_estimator)
        loss = loss + cfg.kl_coef * aggregate(kl, mask, cfg.aggregation, normaliser)
        metrics["train/kl"] = float(masked_mean(kl.detach(), mask))
    if entropy is not None:
        ent = entropy_loss(mask, entropy=entropy)
        metrics["train/entropy"] = float(ent.metrics["entropy"])
        if cfg.entropy_coef > 0:
            loss = loss + cfg.entropy_coef * aggregate(ent.loss_mat, mask, cfg.aggregation, normaliser)
    if "rollout_logprobs" in micro_batch.keys():
        # The trainer's log-probs before the update (pi_old), not the current ones: after the first
        # mini-batch those have moved, and the policy's own drift is not a rollout-vs-trainer gap.
        gap = (old - micro_batch["rollout_logprobs"]).abs()
        metrics["train/logprob_mismatch_mean"] = float(masked_mean(gap, mask))
        metrics["train/logprob_mismatch_max"] = float(masked_max(gap, mask))
    return loss, metrics
