"""DAPO's data-side techniques (Yu et al. 2025, "DAPO", arXiv 2503.14476): dynamic sampling and
overlong reward shaping. RLinf documents both but does not implement them (DESIGN.md section 4, 7).

Dynamic sampling (DAPO section 3.2, eq. 11). A group whose samples all got the same reward (all
right or all wrong) has zero group-relative advantage, so it contributes no gradient but still
dilutes the batch. DAPO keeps generating until the batch holds ``target_groups`` groups with
non-identical rewards. :class:`DynamicSamplingBuffer` is the bookkeeping for that loop; it never
generates: the runner drives it::

    buffer = DynamicSamplingBuffer(target_groups=32, max_extra_rounds=4, group_size=8)
    while buffer.needs_more():
        samples, rewards = generate_and_score(next_prompts())      # one generation round
        buffer.add(samples, rewards)
    result = buffer.take()   # .samples (first 32 informative groups), .cap_reached, .metrics

Overlong reward shaping (DAPO section 3.4, eq. 13): a soft length penalty instead of a cliff, so a
correct answer that runs slightly long is not punished like a wrong one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

__all__ = [
    "DynamicSamplingBuffer",
    "DynamicSamplingResult",
    "group_is_informative",
    "overlong_penalty",
]


def group_is_informative(
    rewards: torch.Tensor, group_size: int, atol: float = 1e-6
) -> torch.Tensor:
    """``[B // group_size]`` bool: does the group's reward spread (max - min) exceed ``atol``?

    Groups are consecutive runs of ``group_size`` samples. ``atol`` absorbs float noise from
    model-based rewards; with 0/1 verifier rewards any value below 1 gives the same answer.
    """
    if rewards.dim() != 1:
        raise ValueError(f"rewards must be [B], got {tuple(rewards.shape)}")
    if group_size <= 0 or rewards.shape[0] % group_size:
        raise ValueError(f"group_size={group_size} must divide the batch size {rewards.shape[0]}")
    grouped = rewards.reshape(-1, group_size)
    return (grouped.amax(dim=1) - grouped.amin(dim=1)) > atol


@dataclass(frozen=True)
class DynamicSamplingResult:
    """What :meth:`DynamicSamplingBuffer.take` hands to the trainer.

    Attributes:
        samples: the kept samples concatenated along dim 0 (exactly ``target_groups * group_size``
            when the batch filled; fewer if the cap was hit), or None if nothing was kept.
        num_groups: informative groups in ``samples``.
        cap_reached: True if generation stopped at ``max_extra_rounds`` before the batch filled.
        metrics: groups seen / kept / dropped (uninformative) / surplus, and rounds used.
    """

    samples: Any
    num_groups: int
    cap_reached: bool
    metrics: dict[str, float]


class DynamicSamplingBuffer:
    """Accumulates informative groups over generation rounds until a batch is full (DAPO eq. 11).

    Args:
        target_groups: informative groups per training batch.
        max_extra_rounds: generation rounds allowed beyond the first. When they are used up the
            buffer stops asking for more and :meth:`take` returns what it has with
            ``cap_reached=True`` (training on a smaller batch beats stalling on a task the
            policy has saturated).
        group_size: samples per group; samples arrive grouped consecutively.
        atol: reward spread at or below which a group counts as uninformative.
    """

    def __init__(
        self, target_groups: int, max_extra_rounds: int, *, group_size: int, atol: float = 1e-6
    ) -> None:
        if target_groups <= 0 or group_size <= 0 or max_extra_rounds < 0:
            raise ValueError(
                "need target_groups > 0, group_size > 0 and max_extra_rounds >= 0; got "
                f"{target_groups}, {group_size}, {max_extra_rounds}"
            )
        self.target_groups = target_groups
        self.group_size = group_size
        self.max_extra_rounds = max_extra_rounds
        self.atol = atol
        self._reset()

    def _reset(self) -> None:
        self._chunks: list[Any] = []
        self.rounds = 0
        self.groups_seen = 0
        self.groups_kept = 0

    @property
    def is_full(self) -> bool:
        return self.groups_kept >= self.target_groups

    @property
    def cap_reached(self) -> bool:
        """All allowed rounds are used and the batch is still not full."""
        return not self.is_full and self.rounds >= 1 + self.max_extra_rounds

    def needs_more(self) -> bool:
        """Should the runner generate another round?"""
        return not self.is_full and not self.cap_reached

    def add(self, samples: Any, rewards: torch.Tensor) -> int:
        """Record one generation round; returns how many of its groups were informative.

        ``samples`` is anything indexable along dim 0 by a LongTensor of sample indices whose
        pieces ``torch.cat`` can join (a tensor, a ``TensorDict``); ``rewards`` is its ``[B]``.
        """
        if not self.needs_more():
            raise RuntimeError(
                "DynamicSamplingBuffer.add after the batch is full or the round cap is reached; "
                "call take() first"
            )
        informative = group_is_informative(rewards, self.group_size, self.atol)
        self.rounds += 1
        self.groups_seen += informative.numel()
        kept_groups = torch.nonzero(informative).squeeze(1)
        if kept_groups.numel():
            offsets = torch.arange(self.group_size, device=kept_groups.device)
            sample_index = (kept_groups[:, None] * self.group_size + offsets).reshape(-1)
            self._chunks.append(samples[sample_index])
            self.groups_kept += kept_groups.numel()
        return int(kept_groups.numel())

    def take(self) -> DynamicSamplingResult:
        """The batch (first ``target_groups`` informative groups in arrival order) and metrics;
        resets the buffer for the next training step."""
        num_groups = min(self.groups_kept, self.target_groups)
        samples = torch.cat(self._chunks)[: num_groups * self.group_size] if self._chunks else None
        metrics = {
            "groups_seen": float(self.groups_seen),
            "groups_kept": float(num_groups),
            "groups_dropped": float(self.groups_seen - self.groups_kept),
            "groups_surplus": float(self.groups_kept - num_groups),
            "rounds": float(self.rounds),
        }
        result = DynamicSamplingResult(samples, num_groups, self.cap_reached, metrics)
        self._reset()
        return result


def overlong_penalty(
    response_lengths: torch.Tensor,
    max_response_length: int,
    buffer_length: int,
    penalty_factor: float = 1.0,
) -> torch.Tensor:
    """DAPO eq. 13 soft overlong punishment, added to the task reward (``[B]`` floats):

    * ``0`` if ``len <= max - buffer``;
    * ``penalty_factor * ((max - buffer) - len) / buffer`` if ``max - buffer < len <= max``
      (linear from 0 down to ``-penalty_factor``);
    * ``-penalty_factor`` if ``len > max``.
    """
    if not 0 < buffer_length <= max_response_length:
        raise ValueError(
            f"need 0 < buffer_length <= max_response_length; got {buffer_length}, "
            f"{max_response_length}"
        )
    lengths = (
        response_lengths
        if response_lengths.is_floating_point()
        else response_lengths.to(torch.get_default_dtype())
    )
    expected = max_response_length - buffer_length
    ramp = (expected - lengths) / buffer_length
    penalty = ramp.clamp(min=-1.0, max=0.0)
    return penalty_factor * penalty
