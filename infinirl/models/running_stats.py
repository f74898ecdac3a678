"""Running mean and variance of observation vectors, as module buffers.

Chan et al.'s parallel update (the one gymnasium's ``NormalizeObservation`` uses), in float64
buffers: ``state_dict`` includes them, so a trainer's statistics reach its rollout with every
weight sync and are restored on resume. Used by the embodied policies' observation normaliser
(``components/embodied_policy.py``), the per-robot-kind state normaliser
(``models/state_normalizer.py``) and the residual VLA policy's input standardisation
(``models/vla/residual.py``); it lives here, below ``components``, so models need not import upwards.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["RunningMeanStd"]


class RunningMeanStd(nn.Module):
    """Running mean and (population) variance of vectors of ``shape``, as float64 buffers."""

    def __init__(self, shape: Sequence[int], epsilon: float = 1e-4):
        super().__init__()
        self.register_buffer("mean", torch.zeros(tuple(shape), dtype=torch.float64))
        self.register_buffer("var", torch.ones(tuple(shape), dtype=torch.float64))
        self.register_buffer("count", torch.tensor(float(epsilon), dtype=torch.float64))

    @torch.no_grad()
    def update(self, batch: torch.Tensor) -> None:
        """Fold in ``batch`` ``[N, *shape]``."""
        batch = batch.reshape(-1, *self.mean.shape).to(torch.float64)
        if batch.shape[0] == 0:
            return
        batch_mean = batch.mean(dim=0)
        batch_var = batch.var(dim=0, unbiased=False)
        n = float(batch.shape[0])
        delta = batch_mean - self.mean
        total = self.count + n
        new_mean = self.mean + delta * n / total
        m2 = self.var * self.count + batch_var * n + delta.pow(2) * self.count * n / total
        self.mean.copy_(new_mean)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def normalize(self, x: torch.Tensor, clip: float) -> torch.Tensor:
        std = torch.sqrt(self.var + 1e-8)
        out = (x.to(torch.float64) - self.mean) / std
        return out.clamp(-clip, clip).to(torch.float32)
