"""A linear readout refitted in closed form on everything it has been shown: ridge regression from
inputs ``x`` to targets ``y`` through running sufficient statistics.

What it is for: a frozen network's features may hold a quantity (where an object is) along a
direction of small variance that a small network trained by RL picks up slowly, while a linear map
fitted by least squares recovers it at once (``scripts/diagnose_vla_episodes.py --probe`` measures
it). In simulation the quantity is observable during training (the simulator's state), so a
readout fitted on training batches turns it into a few well-scaled inputs that the deployed policy
computes from its features alone.

The fit: the inputs are standardised by their running mean and std, the coefficients solve
``(C + penalty * I) b = c`` with ``C`` the inputs' correlation matrix and ``c`` their covariance
with each target (so ``penalty`` is scale-free), and the output is the prediction standardised by
each target's running mean and std, clipped. Targets that have not varied read 0. Accumulating is
order- and split-invariant (sums, float64); :meth:`refit` is the only place the map changes, so a
caller keeps it fixed between refits (e.g. while a PPO update reads it).
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RidgeReadout"]

_MIN_VARIANCE = 1e-12  # a target or input whose variance is below this has not varied: it reads 0


class RidgeReadout(nn.Module):
    """Ridge regression ``[B, in_dim] -> [B, out_dim]`` on running sums; starts unfitted (reads 0).

    Args:
        in_dim, out_dim: the widths of ``x`` and ``y``.
        penalty: the ridge term added to the standardised inputs' correlation matrix (> 0).
        clip: the standardised prediction's bound.
    """

    def __init__(self, in_dim: int, out_dim: int, penalty: float = 1e-3, clip: float = 10.0):
        super().__init__()
        if in_dim < 1 or out_dim < 1:
            raise ValueError(f"RidgeReadout needs in_dim and out_dim >= 1, got {in_dim} and {out_dim}")
        if not penalty > 0:
            raise ValueError(f"RidgeReadout's penalty must be > 0, got {penalty}")
        self.penalty, self.clip = float(penalty), float(clip)
        f64 = torch.float64
        self.register_buffer("count", torch.zeros((), dtype=f64))
        self.register_buffer("sum_x", torch.zeros(in_dim, dtype=f64))
        self.register_buffer("sum_y", torch.zeros(out_dim, dtype=f64))
        self.register_buffer("sum_yy", torch.zeros(out_dim, dtype=f64))
        self.register_buffer("sum_xx", torch.zeros(in_dim, in_dim, dtype=f64))
        self.register_buffer("sum_xy", torch.zeros(in_dim, out_dim, dtype=f64))
        # the fitted map on raw inputs (standardisation folded in); the refit count marks it fitted
        self.register_buffer("weight", torch.zeros(in_dim, out_dim, dtype=f64))
        self.register_buffer("bias", torch.zeros(out_dim, dtype=f64))
        self.register_buffer("fitted_on", torch.zeros((), dtype=f64))

    def _apply(self, fn, recurse=True):
        # a cast of the enclosing policy (.float(), .to(bfloat16)) moves the sums but keeps them float64:
        # sums of squares over many batches lose the fit in lower precision
        kept = dict(self._buffers)
        super()._apply(fn, recurse)
        for name, buffer in kept.items():
            if buffer is not None:
                self._buffers[name] = buffer.to(self._buffers[name].device)
        return self

    @property
    def fitted(self) -> bool:
        return float(self.fitted_on) > 0

    def _rows(self, x: torch.Tensor, y: torch.Tensor | None = None):
        x = torch.as_tensor(x).to(self.sum_x.device, torch.float64).reshape(-1, self.sum_x.shape[0])
        if y is None:
            return x
        y = torch.as_tensor(y).to(self.sum_y.device, torch.float64).reshape(-1, self.sum_y.shape[0])
        if len(x) != len(y):
            raise ValueError(f"RidgeReadout: {len(x)} input rows against {len(y)} target rows")
        return x, y

    @torch.no_grad()
    def accumulate(self, x: torch.Tensor, y: torch.Tensor) -> None:
        """Folds the rows of ``x`` ``[N, in_dim]`` and ``y`` ``[N, out_dim]`` into the sums."""
        x, y = self._rows(x, y)
        self.count += len(x)
        self.sum_x += x.sum(0)
        self.sum_y += y.sum(0)
        self.sum_yy += (y * y).sum(0)
        self.sum_xx += x.T @ x
        self.sum_xy += x.T @ y

    @torch.no_grad()
    def refit(self) -> None:
        """Solves the ridge problem on every row accumulated so far (a no-op before any)."""
        n = float(self.count)
        if n < 2:
            return
        mean_x, mean_y = self.sum_x / n, self.sum_y / n
        cov_xx = self.sum_xx / n - torch.outer(mean_x, mean_x)
        cov_xy = self.sum_xy / n - torch.outer(mean_x, mean_y)
        var_x = cov_xx.diagonal().clamp_min(0.0)
        var_y = (self.sum_yy / n - mean_y * mean_y).clamp_min(0.0)
        live_x, live_y = var_x > _MIN_VARIANCE, var_y > _MIN_VARIANCE
        std_x = torch.where(live_x, var_x.sqrt(), torch.ones_like(var_x))
        std_y = torch.where(live_y, var_y.sqrt(), torch.ones_like(var_y))
        corr = cov_xx / torch.outer(std_x, std_x)
        corr = corr * torch.outer(live_x, live_x)  # constant inputs neither help nor hurt
        system = corr + self.penalty * torch.eye(len(corr), dtype=corr.dtype, device=corr.device)
        coef = torch.linalg.solve(system, (cov_xy / std_x[:, None]) * live_x[:, None])
        weight = coef / std_x[:, None] / std_y[None, :] * live_y[None, :]
        self.weight.copy_(weight)
        self.bias.copy_(-(mean_x @ weight))
        self.fitted_on.fill_(n)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The standardised prediction ``[B, out_dim]`` (float32; zeros until the first fit)."""
        rows = self._rows(x)
        if not self.fitted:
            return torch.zeros(len(rows), self.sum_y.shape[0], device=x.device)
        return (rows @ self.weight + self.bias).clamp(-self.clip, self.clip).to(torch.float32).to(x.device)

    @torch.no_grad()
    def score(self, x: torch.Tensor, y: torch.Tensor) -> float:
        """R² of the present map on ``(x, y)`` averaged over the targets that vary in them (nan before
        the first fit or without such targets): judged on a batch before it is folded in, a held-out
        score."""
        if not self.fitted:
            return float("nan")
        x, y = self._rows(x, y)
        n = float(self.fitted_on)
        mean_y = self.sum_y / n
        std_y = (self.sum_yy / n - mean_y * mean_y).clamp_min(0.0).sqrt()
        predicted = (x @ self.weight + self.bias) * std_y + mean_y
        spread = ((y - y.mean(0)) ** 2).sum(0)
        varies = spread > _MIN_VARIANCE * len(y)
        if not bool(varies.any()):
            return float("nan")
        r2 = 1.0 - ((predicted - y) ** 2).sum(0)[varies] / spread[varies]
        return float(r2.mean())
