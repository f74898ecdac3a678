"""Which transitions a mini-batch takes: seeded draws over the live history, with exact resume.

Each draw is uniform over all live transitions or, with probability ``recent_fraction``, uniform
over the newest ``recent_transitions`` of them. The draws come from the sampler's own
``numpy.random.Generator`` (PCG64), so the sequence of batches is a function of the seed and the
sequence of appends (and evictions) only; :meth:`TransitionSampler.state_dict` carries the
generator's state for a restarted run to continue the same stream.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["SamplingSpec", "TransitionSampler"]


@dataclass(frozen=True, kw_only=True)
class SamplingSpec:
    seed: int | list[int] = 0
    recent_fraction: float = 0.0  # share of draws taken from the newest `recent_transitions`
    recent_transitions: int = 0

    def __post_init__(self):
        if not 0.0 <= self.recent_fraction <= 1.0:
            raise ValueError(f"sampling.recent_fraction must be in [0, 1], got {self.recent_fraction}")
        if self.recent_fraction > 0 and self.recent_transitions < 1:
            raise ValueError("sampling.recent_transitions must be >= 1 when recent_fraction > 0")


class TransitionSampler:
    def __init__(self, spec: SamplingSpec):
        self.spec = spec
        self._rng = np.random.default_rng(spec.seed)
        self.batches = 0  # batches drawn so far (a position in the stream)

    def draw(self, first: int, end: int, batch_size: int) -> np.ndarray:
        """``batch_size`` absolute positions in ``[first, end)``, sorted ascending (a batch is a set
        of independent draws; sorted rows read each segment's files in order)."""
        if end <= first:
            raise ValueError("cannot sample from an empty replay store")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        positions = self._rng.integers(first, end, size=batch_size)
        if self.spec.recent_fraction > 0:
            window = min(self.spec.recent_transitions, end - first)
            recent = self._rng.integers(end - window, end, size=batch_size)
            take = self._rng.random(batch_size) < self.spec.recent_fraction
            positions = np.where(take, recent, positions)
        self.batches += 1
        positions.sort()
        return positions

    def state_dict(self) -> dict[str, Any]:
        return {"rng": self._rng.bit_generator.state, "batches": self.batches}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self._rng.bit_generator.state = state["rng"]
        self.batches = int(state["batches"])
