"""Combining logged training metrics over micro-batches, ranks and optimizer steps.

A metric is reported per micro-batch (or per step, or per rank) and logged once per iteration. Most
are means and combine as means, but an extreme does not: the mean of per-micro-batch maxima hides
the one token with an importance weight of 1e3 among 16 micro-batches (it reports ~60). So the
name decides: a key ending in ``_max`` combines by max, one ending in ``_min`` by min, every other
one by the mean of the parts (each part weighs the same).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Literal

import torch

__all__ = ["MetricReducer", "metric_reduction"]

Reduction = Literal["mean", "max", "min"]


def metric_reduction(key: str) -> Reduction:
    """How the metric ``key`` combines over parts: ``max`` (``..._max``), ``min`` (``..._min``), or
    ``mean``."""
    if key.endswith("_max"):
        return "max"
    if key.endswith("_min"):
        return "min"
    return "mean"


def _extreme(a, b, how: Reduction):
    """The max or min of two floats or tensors; a NaN in either wins (it must stay visible)."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        device = a.device if isinstance(a, torch.Tensor) else b.device
        a, b = torch.as_tensor(a, device=device), torch.as_tensor(b, device=device)
        return torch.maximum(a, b) if how == "max" else torch.minimum(a, b)
    if math.isnan(a) or math.isnan(b):
        return math.nan
    return max(a, b) if how == "max" else min(a, b)


class MetricReducer:
    """Folds metric dicts (floats or tensors: tensors stay on their device, no sync per part) into
    one: per key a running sum and count for means, the running extreme for ``_max`` / ``_min``.

    Reducers merge (:meth:`merge`), so each rank folds its micro-batches and the ranks' reducers
    then fold into one; :meth:`result` gives the floats."""

    def __init__(self) -> None:
        self.values: dict[str, object] = {}
        self.counts: dict[str, int] = {}

    def add(self, metrics: Mapping[str, object]) -> None:
        """The metrics of one more part (a micro-batch, a step)."""
        for key, value in metrics.items():
            self._fold(key, value, 1)

    def merge(self, other: MetricReducer) -> None:
        """Another reducer's parts (another rank's)."""
        for key, value in other.values.items():
            self._fold(key, value, other.counts[key])

    def as_floats(self) -> MetricReducer:
        """A copy holding Python floats (to send to other ranks: no tensors, one sync here)."""
        copy = MetricReducer()
        copy.values = {key: float(value) for key, value in self.values.items()}
        copy.counts = dict(self.counts)
        return copy

    def result(self) -> dict[str, float]:
        return {key: float(value) / self.counts[key] if metric_reduction(key) == "mean" else float(value)
                for key, value in self.values.items()}

    def _fold(self, key: str, value, count: int) -> None:
        if key not in self.values:
            self.values[key], self.counts[key] = value, count
            return
        how = metric_reduction(key)
        current = self.values[key]
        self.values[key] = current + value if how == "mean" else _extreme(current, value, how)
        self.counts[key] += count
