"""Cutting a rank's batch into micro-batches, and trimming the columns a forward pass computes.

All collectives must match across ranks: a rank with fewer micro-batches than the busiest rank
runs zero-loss *filler* passes (:func:`filler_batch`) until every rank made
:func:`micro_batch_plan`'s number of passes.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.distributed as dist
from tensordict import TensorDict

from infinirl.data.batch import ATTENTION_MASK, INPUT_IDS, POSITION_IDS, RESPONSE_MASK

__all__ = ["as_tensordict", "filler_batch", "first_scored_column", "micro_batch_plan", "pad_columns", "used_width"]


def as_tensordict(batch: TensorDict | Mapping[str, torch.Tensor]) -> TensorDict:
    """A token batch as a ``TensorDict`` (a plain mapping needs ``input_ids``)."""
    if isinstance(batch, TensorDict):
        return batch
    if INPUT_IDS not in batch:
        raise KeyError(f"batch needs {INPUT_IDS!r}; got keys {sorted(batch)}")
    return TensorDict(dict(batch), batch_size=[batch[INPUT_IDS].shape[0]])


def micro_batch_plan(batch: TensorDict, micro_batch_size: int, device: torch.device) -> tuple[list[TensorDict], int]:
    """This rank's micro-batches, and how many passes every rank must make (the global max).

    FSDP all-gathers parameters in every forward and reduce-scatters gradients in every
    backward; a rank that stopped early would leave the others waiting forever. Collective.
    """
    size = batch.batch_size[0]
    micro_batches = list(batch.split(micro_batch_size)) if size else []
    count = torch.tensor([len(micro_batches)], device=device)
    dist.all_reduce(count, op=dist.ReduceOp.MAX)
    return micro_batches, int(count.item())


def filler_batch(device: torch.device) -> TensorDict:
    """One row of one token: a pass that joins the collectives at the least cost."""
    one = torch.ones(1, 1, dtype=torch.long, device=device)
    return TensorDict({INPUT_IDS: one * 0, ATTENTION_MASK: one, POSITION_IDS: one * 0}, batch_size=[1], device=device)


def used_width(attention_mask: torch.Tensor) -> int:
    """Columns up to the last attended token of any row: trailing all-pad columns are skipped."""
    positions = torch.arange(1, attention_mask.shape[1] + 1, device=attention_mask.device)
    return max(1, int((positions * (attention_mask != 0)).max()))


def pad_columns(scores: torch.Tensor, width: int, left: int = 0) -> torch.Tensor:
    """Zero columns: ``left`` before the scores and as many after as make ``width``."""
    if scores.shape[1] == width and not left:
        return scores
    return torch.nn.functional.pad(scores, (left, width - left - scores.shape[1]))


def first_scored_column(micro_batch: TensorDict, width: int) -> int:
    """The first column whose logits any row's response needs: one before the earliest response
    token (``response_mask``), or 0 when the batch does not say which tokens are responses."""
    mask = micro_batch.get(RESPONSE_MASK, None)
    if mask is None or width < 2:
        return 0
    mask = mask[:, :width].to(torch.bool)
    if not bool(mask.any()):
        return 0
    first = int(mask.any(dim=0).to(torch.int8).argmax())
    return max(0, first - 1)
