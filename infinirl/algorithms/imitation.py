"""Imitation losses: behaviour cloning (BC) and DAgger.

Both are supervised on expert actions; they differ only in *which states* are labelled. BC uses
states from expert demonstrations; DAgger (Ross et al. 2011, "A Reduction of Imitation Learning and
Structured Prediction to No-Regret Online Learning") runs the learner, asks the expert (or a human
intervening on a real robot) to label the states the learner visited, and trains on the aggregate.
The loss is the same function; the data pipeline decides which one you are doing.

``mask`` (optional) drops what has no label: ``[B]`` per sample (e.g. steps of an intervention-based
rollout where the human did not take over; the loss is averaged within each sample first), or
shaped like the loss, per element (e.g. prompt and padding tokens of an LLM SFT batch).
"""

from __future__ import annotations

import torch

from infinirl.algorithms.masking import masked_mean

__all__ = ["bc_mse_loss", "bc_nll_loss"]


def _masked_average(loss: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean over valid elements: ``mask`` is per sample (``[B]``) or per element (loss's shape)."""
    if mask is None:
        return loss.mean()
    if mask.shape == loss.shape:
        return masked_mean(loss, mask)
    if mask.shape == loss.shape[:1]:
        return masked_mean(loss.reshape(loss.shape[0], -1).mean(dim=1), mask)
    raise ValueError(
        f"mask must be [B]={tuple(loss.shape[:1])} or shaped like the loss {tuple(loss.shape)}; "
        f"got {tuple(mask.shape)}"
    )


def bc_mse_loss(
    predicted_actions: torch.Tensor,
    expert_actions: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean squared error to the expert's continuous actions (``[B, ...]``, e.g. ``[B, C, D]`` for
    chunks of ``C`` actions of ``D`` dims), averaged over action elements then over valid samples:
    without a mask it equals ``F.mse_loss``. The regression objective of deterministic or
    flow/diffusion-free continuous policies."""
    if predicted_actions.shape != expert_actions.shape:
        raise ValueError(
            f"predicted {tuple(predicted_actions.shape)} and expert {tuple(expert_actions.shape)} "
            "actions must have the same shape"
        )
    return _masked_average((predicted_actions - expert_actions.detach()) ** 2, mask)


def bc_nll_loss(expert_logprobs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Negative log-likelihood of the expert's actions under the policy, ``-mean log pi(a*|s)``.

    ``expert_logprobs`` is ``[B]`` (joint log-prob per sample) or ``[B, ...]`` (e.g. per action
    token), so it fits stochastic policies, discretised-action VLAs and LLMs.
    """
    return _masked_average(-expert_logprobs, mask)
