"""Groups of samples that answer the same prompt (or start from the same env reset state).

Group-relative estimators (GRPO, Dr.GRPO, RLOO, REINFORCE++-baseline, embodied GRPO) compare each
sample only with its siblings. A group is given either as ``group_size`` (the rollout repeats each
prompt ``group_size`` times consecutively, the usual layout) or as explicit ``group_ids`` (any
integer label per sample, in any order: what survives after filtering or reordering).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["GroupStats", "group_index", "group_stats"]


def group_index(
    batch_size: int,
    *,
    group_size: int | None = None,
    group_ids: torch.Tensor | None = None,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, int]:
    """Dense group number ``0..G-1`` of every sample, and ``G``. Give exactly one of the two."""
    if (group_size is None) == (group_ids is None):
        raise ValueError("give exactly one of group_size (consecutive groups) or group_ids")
    if group_ids is not None:
        if group_ids.shape != (batch_size,):
            raise ValueError(
                f"group_ids must have shape ({batch_size},), one label per sample; "
                f"got {tuple(group_ids.shape)}"
            )
        labels, index = torch.unique(group_ids, return_inverse=True)
        return index.to(device), labels.numel()
    if group_size <= 0 or batch_size % group_size:
        raise ValueError(
            f"group_size={group_size} must be positive and divide the batch size {batch_size} "
            "(consecutive samples form a group); pass group_ids for uneven groups"
        )
    index = torch.arange(batch_size, device=device) // group_size
    return index, batch_size // group_size


@dataclass(frozen=True)
class GroupStats:
    """Per-sample statistics of the sample's own group (each a ``[B]`` tensor)."""

    count: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor  # unbiased (Bessel) std as in DeepSeekMath's GRPO; 0 for a group of one


def group_stats(scores: torch.Tensor, index: torch.Tensor, num_groups: int) -> GroupStats:
    """Count, mean and unbiased std of ``scores`` ([B]) within each sample's group.

    A group whose scores are all equal gets exactly its common value as mean and exactly 0 as std.
    Summing then dividing does not guarantee that (seven float32 rewards of 0.1 average to
    0.1 - 7e-9), and ``/ (std + eps)`` would blow the rounding error up into a spurious advantage
    of ~0.01 for a group that carries no signal at all.
    """
    if scores.dim() != 1:
        raise ValueError(f"group scores must be [B], got shape {tuple(scores.shape)}")
    index = index.to(scores.device)
    count = scores.new_zeros(num_groups).index_add_(0, index, torch.ones_like(scores))
    mean = scores.new_zeros(num_groups).index_add_(0, index, scores) / count.clamp(min=1.0)
    empty = scores.new_zeros(num_groups)
    highest = empty.scatter_reduce(0, index, scores, "amax", include_self=False)
    lowest = empty.scatter_reduce(0, index, scores, "amin", include_self=False)
    constant = (highest == lowest)[index]
    squared = scores.new_zeros(num_groups).index_add_(0, index, (scores - mean[index]) ** 2)
    std = torch.sqrt(squared / (count - 1).clamp(min=1.0))[index]
    return GroupStats(
        count=count[index],
        mean=torch.where(constant, scores, mean[index]),
        std=torch.where(constant, torch.zeros_like(std), std),
    )
