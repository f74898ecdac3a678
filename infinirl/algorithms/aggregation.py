"""Turning a per-token loss matrix into one scalar, independently of micro-batching and DP.

The problem. A mini-batch (one optimizer step) is split over data-parallel (DP) ranks and, on each
rank, into micro-batches for gradient accumulation. If every micro-batch takes its *own* mean, the
gradient depends on the split: a 10-token micro-batch and a 1000-token one get equal weight, so the
same data trained with a different ``micro_batch_size`` or GPU count gives a different model.

The fix. Every mode is ``loss = (sum of contributions) / normaliser`` where the contributions are
per-row and the normaliser is a property of the *whole mini-batch*, computed once before the
micro-batch loop. Each micro-batch returns ``sum(its contributions) / global normaliser``; summing
those over all micro-batches and all ranks gives the full-batch loss exactly (hence the same
gradient, up to float rounding).

Trainer contract::

    # once per mini-batch, on every rank, over the rank's whole share of the mini-batch:
    n = aggregation_normaliser(response_mask_of_my_share, mode, **mode_kwargs)
    n = all_reduce_sum(n)           # every mode's normaliser is additive over disjoint shards
    for micro in my_share.split(micro_batch_size):
        loss_mat = ...              # per-token losses of this micro-batch, [b, L]
        aggregate(loss_mat, micro.response_mask, mode, n).backward()   # no "/ num_micro_batches"
    # gradients must be SUMMED across DP ranks. A DP wrapper that AVERAGES (DDP, FSDP) divides by
    # the world size W: multiply each micro-batch loss by W to undo it.

Modes (registered in ``AGGREGATIONS``; ``n_i`` = valid tokens of sequence ``i``, ``S`` = number
of sequences with at least one valid token; empty rows, e.g. DP padding, count for nothing):

* ``token-mean``: ``sum_{i,t} l_it / sum_i n_i``: every token weighs the same (DAPO, Yu et al.
  2025, eq. 12 "token-level policy gradient loss").
* ``seq-mean-token-sum``: ``sum_{i,t} l_it / S``.
* ``seq-mean-token-mean``: ``sum_i (sum_t l_it / n_i) / S``: every sequence weighs the same
  (original GRPO, Shao et al. 2024, eq. 3).
* ``seq-mean-token-sum-norm``: ``sum_{i,t} l_it / (S * max_response_length)``: Dr.GRPO (Liu et al.
  2025), which replaces GRPO's ``1/n_i`` with a constant so long answers are not under-weighted.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from infinirl.algorithms.masking import zero_outside
from infinirl.algorithms.registry import AGGREGATIONS

__all__ = ["AggregationMode", "aggregate", "aggregate_locally", "aggregation_normaliser"]


@dataclass(frozen=True)
class AggregationMode:
    """One aggregation mode: how rows contribute, and the mini-batch normaliser they share."""

    name: str
    contributions: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (loss, mask) -> scalar
    normaliser: Callable[..., float]  # (mask, **kwargs) -> float


def _rows(tensor: torch.Tensor) -> torch.Tensor:
    """View any ``[B, ...]`` tensor as ``[B, K]`` (a ``[B]`` per-sample loss becomes ``[B, 1]``)."""
    return tensor.reshape(tensor.shape[0], -1)


def _token_sum(loss: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return zero_outside(loss, mask).sum()


def _sum_of_sequence_means(loss: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    per_row = zero_outside(loss, mask).sum(dim=1) / mask.sum(dim=1).clamp(min=1.0)
    return per_row.sum()


def _count_tokens(mask: torch.Tensor) -> float:
    return float(mask.sum().item())


def _count_sequences(mask: torch.Tensor) -> float:
    return float((mask.sum(dim=1) > 0).sum().item())


def _count_sequences_times_length(mask: torch.Tensor, *, max_response_length: int) -> float:
    if max_response_length <= 0:
        raise ValueError(f"max_response_length must be positive, got {max_response_length}")
    return _count_sequences(mask) * float(max_response_length)


for _mode in (
    AggregationMode("token-mean", _token_sum, _count_tokens),
    AggregationMode("seq-mean-token-sum", _token_sum, _count_sequences),
    AggregationMode("seq-mean-token-mean", _sum_of_sequence_means, _count_sequences),
    AggregationMode("seq-mean-token-sum-norm", _token_sum, _count_sequences_times_length),
):
    AGGREGATIONS.add(_mode.name, _mode)


def aggregation_normaliser(response_mask: torch.Tensor, mode: str, **mode_kwargs: int) -> float:
    """The normaliser of ``mode`` for the mini-batch (or this rank's share) with this mask.

    Call it on the *whole* mini-batch, never per micro-batch. It is additive over disjoint shards,
    so with DP each rank computes its own and the trainer all-reduces with SUM.
    ``seq-mean-token-sum-norm`` needs ``max_response_length`` (Dr.GRPO's constant).
    """
    spec: AggregationMode = AGGREGATIONS.get(mode)
    try:
        return spec.normaliser(_rows(response_mask).to(torch.float64), **mode_kwargs)
    except TypeError as error:
        raise TypeError(f"aggregation mode {mode!r}: {error}") from None


def aggregate(
    loss_mat: torch.Tensor,
    response_mask: torch.Tensor,
    mode: str,
    normaliser: float | torch.Tensor,
) -> torch.Tensor:
    """``sum(contributions of this micro-batch) / normaliser``, a differentiable scalar.

    ``loss_mat`` and ``response_mask`` are ``[b, L]`` (any ``[b, ...]`` works: trailing dims are
    flattened). ``normaliser`` comes from :func:`aggregation_normaliser` over the whole mini-batch
    (a float, or a 0-dim tensor after an all-reduce).
    A normaliser of 0 means the mini-batch has nothing to train on: the loss is 0, still attached to
    the graph so that every rank runs the same backward (collectives must not deadlock).
    """
    if loss_mat.shape != response_mask.shape:
        raise ValueError(
            f"loss_mat {tuple(loss_mat.shape)} and response_mask {tuple(response_mask.shape)} "
            "must have the same shape"
        )
    spec: AggregationMode = AGGREGATIONS.get(mode)
    loss = _rows(loss_mat)
    mask = _rows(response_mask).to(dtype=loss.dtype)
    total = spec.contributions(loss, mask)
    if isinstance(normaliser, torch.Tensor):
        # No branch on the value (no device sync; traceable by torch.compile). A normaliser of 0
        # means nothing counts, so every contribution, hence ``total``, is already 0: divide by 1.
        return total / torch.where(normaliser > 0, normaliser, torch.ones_like(normaliser))
    if normaliser <= 0:
        return total * 0.0
    return total / normaliser


def aggregate_locally(
    loss_mat: torch.Tensor, response_mask: torch.Tensor, mode: str, **mode_kwargs: int
) -> torch.Tensor:
    """Aggregate one tensor on its own (its mask is the whole batch): for metrics, evaluation, and
    single-micro-batch training."""
    normaliser = aggregation_normaliser(response_mask, mode, **mode_kwargs)
    return aggregate(loss_mat, response_mask, mode, normaliser)
