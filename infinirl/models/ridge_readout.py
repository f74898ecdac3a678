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

With ``groups > 1`` it is one readout per group of rows, each row carrying an integer key (e.g. a
hash of its task's instruction): a quantity can sit along different directions of the features
for different tasks, which one linear map across tasks reads far less exactly than one per task.
Keys take the free groups in the order they first appear (sorted within a batch); a row whose key
has no fitted group reads 0.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RidgeReadout"]

_MIN_VARIANCE = 1e-12  # a target or input whose variance is below this has not varied: it reads 0


class RidgeReadout(nn.Module):
    """Ridge regression ``[B, in_dim] -> [B, out_dim]`` on running sums, one per group of rows;
    starts unfitted (reads 0).

    Args:
        in_dim, out_dim: the widths of ``x`` and ``y``.
        penalty: the ridge term added to the standardised inputs' correlation matrix (> 0).
        clip: the standardised prediction's bound.
        groups: how many keyed groups it can hold (1: every row in one group, no keys needed).
    """

    def __init__(self, in_dim: int, out_dim: int, penalty: float = 1e-3, clip: float = 10.0, groups: int = 1):
        super().__init__()
        if in_dim < 1 or out_dim < 1 or groups < 1:
            raise ValueError(f"RidgeReadout needs in_dim, out_dim and groups >= 1, got {in_dim}, {out_dim} and "
                             f"{groups}")
        if not penalty > 0:
            raise ValueError(f"RidgeReadout's penalty must be > 0, got {penalty}")
        self.penalty, self.clip, self.groups = float(penalty), float(clip), int(groups)
        f64, g = torch.float64, int(groups)
        self.register_buffer("keys", torch.zeros(g, dtype=torch.int64))  # 0: a free group
        self.register_buffer("count", torch.zeros(g, dtype=f64))
        self.register_buffer("sum_x", torch.zeros(g, in_dim, dtype=f64))
        self.register_buffer("sum_y", torch.zeros(g, out_dim, dtype=f64))
        self.register_buffer("sum_yy", torch.zeros(g, out_dim, dtype=f64))
        self.register_buffer("sum_xx", torch.zeros(g, in_dim, in_dim, dtype=f64))
        self.register_buffer("sum_xy", torch.zeros(g, in_dim, out_dim, dtype=f64))
        # the fitted maps on raw inputs (standardisation folded in); a group's refit count marks it fitted
        self.register_buffer("weight", torch.zeros(g, in_dim, out_dim, dtype=f64))
        self.register_buffer("bias", torch.zeros(g, out_dim, dtype=f64))
        self.register_buffer("fitted_on", torch.zeros(g, dtype=f64))

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
        """Whether any group is fitted."""
        return bool((self.fitted_on > 0).any())

    def _rows(self, x: torch.Tensor, y: torch.Tensor | None = None):
        x = torch.as_tensor(x).to(self.sum_x.device, torch.float64).reshape(-1, self.sum_x.shape[1])
        if y is None:
            return x
        y = torch.as_tensor(y).to(self.sum_y.device, torch.float64).reshape(-1, self.sum_y.shape[1])
        if len(x) != len(y):
            raise ValueError(f"RidgeReadout: {len(x)} input rows against {len(y)} target rows")
        return x, y

    def _slots(self, keys: torch.Tensor | None, rows: int, claim: bool = False) -> torch.Tensor:
        """The group of each row ``[rows]`` (-1: a key without a group); ``claim`` gives new keys the
        free groups."""
        if self.groups == 1 and keys is None:
            return torch.zeros(rows, dtype=torch.int64, device=self.keys.device)
        if keys is None:
            raise ValueError(f"RidgeReadout with groups={self.groups} needs a key per row")
        keys = torch.as_tensor(keys).to(self.keys.device, torch.int64).reshape(-1)
        if len(keys) != rows or bool((keys == 0).any()):
            raise ValueError(f"RidgeReadout: {len(keys)} keys for {rows} rows (keys must be nonzero)")
        if claim:
            new = [int(k) for k in torch.unique(keys) if not bool((self.keys == k).any())]
            free = (self.keys == 0).nonzero().reshape(-1)
            if len(new) > len(free):
                raise ValueError(f"RidgeReadout holds {self.groups} groups and a batch brings "
                                 f"{int((self.keys != 0).sum()) + len(new)} keys: raise its groups")
            for key, slot in zip(new, free.tolist()):
                self.keys[slot] = key
        match = keys[:, None] == self.keys[None, :]
        return torch.where(match.any(1), match.int().argmax(1), torch.full_like(keys, -1))

    @torch.no_grad()
    def accumulate(self, x: torch.Tensor, y: torch.Tensor, keys: torch.Tensor | None = None) -> None:
        """Folds the rows of ``x`` ``[N, in_dim]`` and ``y`` ``[N, out_dim]`` (of groups ``keys``
        ``[N]``) into the sums."""
        x, y = self._rows(x, y)
        slots = self._slots(keys, len(x), claim=True)
        for slot in torch.unique(slots).tolist():
            xs, ys = x[slots == slot], y[slots == slot]
            self.count[slot] += len(xs)
            self.sum_x[slot] += xs.sum(0)
            self.sum_y[slot] += ys.sum(0)
            self.sum_yy[slot] += (ys * ys).sum(0)
            self.sum_xx[slot] += xs.T @ xs
            self.sum_xy[slot] += xs.T @ ys

    @torch.no_grad()
    def refit(self) -> None:
        """Solves each group's ridge problem on every row it has accumulated (groups with fewer
        than 2 rows stay as they are)."""
        for slot in range(self.groups):
            n = float(self.count[slot])
            if n >= 2:
                self._refit_group(slot, n)

    def _refit_group(self, slot: int, n: float) -> None:
        mean_x, mean_y = self.sum_x[slot] / n, self.sum_y[slot] / n
        cov_xx = self.sum_xx[slot] / n - torch.outer(mean_x, mean_x)
        cov_xy = self.sum_xy[slot] / n - torch.outer(mean_x, mean_y)
        var_x = cov_xx.diagonal().clamp_min(0.0)
        var_y = (self.sum_yy[slot] / n - mean_y * mean_y).clamp_min(0.0)
        live_x, live_y = var_x > _MIN_VARIANCE, var_y > _MIN_VARIANCE
        std_x = torch.where(live_x, var_x.sqrt(), torch.ones_like(var_x))
        std_y = torch.where(live_y, var_y.sqrt(), torch.ones_like(var_y))
        corr = cov_xx / torch.outer(std_x, std_x)
        corr = corr * torch.outer(live_x, live_x)  # constant inputs neither help nor hurt
        system = corr + self.penalty * torch.eye(len(corr), dtype=corr.dtype, device=corr.device)
        coef = torch.linalg.solve(system, (cov_xy / std_x[:, None]) * live_x[:, None])
        weight = coef / std_x[:, None] / std_y[None, :] * live_y[None, :]
        self.weight[slot].copy_(weight)
        self.bias[slot].copy_(-(mean_x @ weight))
        self.fitted_on[slot] = n

    def _standardised(self, rows: torch.Tensor, slots: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each row's standardised prediction and whether its group is fitted."""
        fitted = (slots >= 0) & (self.fitted_on[slots.clamp_min(0)] > 0)
        out = torch.zeros(len(rows), self.sum_y.shape[1], dtype=rows.dtype, device=rows.device)
        for slot in torch.unique(slots[fitted]).tolist():
            mine = slots == slot
            out[mine] = rows[mine] @ self.weight[slot] + self.bias[slot]
        return out, fitted

    def forward(self, x: torch.Tensor, keys: torch.Tensor | None = None) -> torch.Tensor:
        """The standardised prediction ``[B, out_dim]`` (float32; zeros for rows of an unfitted or
        unknown group)."""
        rows = self._rows(x)
        out, _ = self._standardised(rows, self._slots(keys, len(rows)))
        return out.clamp(-self.clip, self.clip).to(torch.float32).to(x.device)

    @torch.no_grad()
    def score(self, x: torch.Tensor, y: torch.Tensor, keys: torch.Tensor | None = None) -> float:
        """R² of the present maps on ``(x, y)``, over the rows of fitted groups, averaged over the
        targets that vary in them (nan without such rows or targets): judged on a batch before it is
        folded in, a held-out score."""
        x, y = self._rows(x, y)
        slots = self._slots(keys, len(x))
        out, fitted = self._standardised(x, slots)
        if not bool(fitted.any()):
            return float("nan")
        safe = slots.clamp_min(0)[fitted]
        n = self.fitted_on[safe][:, None]
        mean_y = self.sum_y[safe] / n
        std_y = (self.sum_yy[safe] / n - mean_y * mean_y).clamp_min(0.0).sqrt()
        predicted, y = out[fitted] * std_y + mean_y, y[fitted]
        spread = ((y - y.mean(0)) ** 2).sum(0)
        varies = spread > _MIN_VARIANCE * len(y)
        if not bool(varies.any()):
            return float("nan")
        r2 = 1.0 - ((predicted - y) ** 2).sum(0)[varies] / spread[varies]
        return float(r2.mean())
