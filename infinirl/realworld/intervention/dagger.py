"""HG-DAgger's data and loss: the human-labelled states, aggregated over iterations, and behaviour
cloning on them.

HG-DAgger (Kelly et al., 2019) rolls out the learner's policy with an expert watching; where the
expert takes over, the states it visits are labelled with its actions. :func:`human_labelled` takes
those rows out of an episode (``intervened`` steps: the observation before the step and the
human's action, which is the executed one), :class:`AggregateDataset` keeps every row ever labelled
(plus demonstrations, all of whose steps are labelled), and :func:`bc_loss` is the cloning loss the
policy is trained on, over the whole aggregate, each iteration.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch

__all__ = ["BC_LOSSES", "AggregateDataset", "bc_loss", "human_labelled"]

BC_LOSSES = ("mse", "gaussian_nll")
_ATANH_LIMIT = 1.0 - 1e-4  # a target of exactly +-1 has no finite pre-squash value


def human_labelled(episode: dict[str, np.ndarray], all_steps: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(states [N, D], actions [N, A])`` of the steps the human acted (``intervened``), or of every
    step with ``all_steps`` (a demonstration). The state is the observation the step started from."""
    steps = len(episode["action"])
    if all_steps:
        rows = np.arange(steps)
    else:
        if "intervened" not in episode:
            raise KeyError("episode has no 'intervened' field: it was recorded without an intervention device")
        rows = np.flatnonzero(np.asarray(episode["intervened"]).reshape(-1) != 0)
    return (np.asarray(episode["state"][:steps][rows], np.float32),
            np.asarray(episode["action"][rows], np.float32))


class AggregateDataset:
    """Every labelled ``(state, action)`` row so far; rows are only ever added."""

    def __init__(self, obs_dim: int, action_dim: int) -> None:
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.states = np.zeros((0, obs_dim), np.float32)
        self.actions = np.zeros((0, action_dim), np.float32)

    def __len__(self) -> int:
        return len(self.states)

    def add(self, states: np.ndarray, actions: np.ndarray) -> int:
        """Append rows; returns how many."""
        states, actions = np.asarray(states, np.float32), np.asarray(actions, np.float32)
        if states.ndim != 2 or states.shape[1] != self.obs_dim or actions.shape != (len(states), self.action_dim):
            raise ValueError(f"AggregateDataset.add: states [N, {self.obs_dim}] and actions [N, {self.action_dim}] "
                             f"expected, got {states.shape} and {actions.shape}")
        self.states = np.concatenate([self.states, states])
        self.actions = np.concatenate([self.actions, actions])
        return len(states)

    def sample(self, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``batch_size`` rows drawn uniformly with replacement."""
        if not len(self):
            raise RuntimeError("AggregateDataset.sample: the dataset is empty (no labelled steps yet)")
        rows = torch.randint(len(self), (batch_size,), generator=generator).numpy()
        return torch.from_numpy(self.states[rows]), torch.from_numpy(self.actions[rows])

    def state_dict(self) -> dict:
        return {"states": self.states.copy(), "actions": self.actions.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.states = np.asarray(state["states"], np.float32)
        self.actions = np.asarray(state["actions"], np.float32)


def bc_loss(mean: torch.Tensor, log_std: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
            kind: Literal["mse", "gaussian_nll"] = "mse") -> torch.Tensor:
    """Behaviour cloning loss of a squashed Gaussian policy (pre-squash ``mean``, ``log_std``,
    ``[B, A]``) on ``target`` actions in ``[-1, 1]``, averaged over the entries ``mask`` keeps
    (``[B]`` rows or ``[B, A]`` entries, 0/1; None: all).

    ``mse``: ``(tanh(mean) - target)^2``; ``gaussian_nll``: ``-log N(atanh(target); mean, exp(log_std))``
    per entry (the tanh change of variables adds a term constant in the parameters, left out), with
    targets clipped to ``+-(1 - 1e-4)`` so that ``atanh`` stays finite.
    """
    if kind == "mse":
        per_entry = (torch.tanh(mean) - target) ** 2
    elif kind == "gaussian_nll":
        u = torch.atanh(target.clamp(-_ATANH_LIMIT, _ATANH_LIMIT))
        per_entry = 0.5 * ((u - mean) / log_std.exp()) ** 2 + log_std + 0.5 * math.log(2 * math.pi)
    else:
        raise ValueError(f"bc loss must be one of {BC_LOSSES}, got {kind!r}")
    if mask is None:
        return per_entry.mean()
    weights = mask.to(per_entry.dtype)
    if weights.dim() == 1:
        weights = weights[:, None].expand_as(per_entry)
    return (per_entry * weights).sum() / weights.sum().clamp_min(1.0)
