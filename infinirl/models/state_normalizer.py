"""Per-embodiment normalisation of the state vector in front of SAC's networks.

Robots of different kinds feed one policy (:class:`~infinirl.realworld.control_loop.PolicyLayout`):
each robot's state is padded with zeros to the longest and followed by a one-hot of its kind. Their
entries mean different things in different units (a Sawyer's hand position in metres, an SO-101's
joint angles in radians), so one set of statistics would describe neither. :class:`EmbodimentStateNormalizer`
keeps a running mean and variance **per embodiment** (the kind read off the one-hot) and maps each
robot's entries to zero mean and unit variance with its own; the one-hot passes through unchanged,
and a robot's padding entries (always 0, variance 0) stay 0.

:class:`NormalizedStateEncoder` puts it in front of an observation encoder (or in front of the
networks when there is none), so it rides the encoder path of :mod:`infinirl.models.sac_encoders`:
one module shared by the actor and the critics, the target critics holding a copy, and the actor's
``state_dict`` (what a robot loads) carrying the statistics. The replay store keeps raw states, so
an off-policy batch is always normalised with the present statistics; the learner folds every
stored episode's states in as it arrives (:meth:`~infinirl.components.sac_learner.SACAgent.observe_states`).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from infinirl.models.running_stats import RunningMeanStd

__all__ = ["EmbodimentStateNormalizer", "NormalizedStateEncoder"]


class EmbodimentStateNormalizer(nn.Module):
    """Running statistics of ``obs_dim``-entry states, one set per embodiment (see the module docstring).

    With ``embodiments > 1`` the last ``embodiments`` entries are the kind one-hot (not normalised);
    with one embodiment every entry is a feature.
    """

    def __init__(self, obs_dim: int, embodiments: int = 1, clip: float = 10.0):
        super().__init__()
        if embodiments < 1:
            raise ValueError(f"embodiments must be >= 1, got {embodiments}")
        self.obs_dim, self.embodiments, self.clip = int(obs_dim), int(embodiments), float(clip)
        self.features = self.obs_dim - (self.embodiments if self.embodiments > 1 else 0)
        if self.features < 1:
            raise ValueError(f"a state of {obs_dim} entries has no features besides {embodiments} one-hot entries")
        self.stats = nn.ModuleList(RunningMeanStd((self.features,)) for _ in range(self.embodiments))

    def kinds(self, state: torch.Tensor) -> torch.Tensor:
        """``[N]`` embodiment index of each row."""
        if self.embodiments == 1:
            return torch.zeros(state.shape[0], dtype=torch.long, device=state.device)
        return state[:, self.features:].argmax(-1)

    @torch.no_grad()
    def update(self, state: torch.Tensor) -> None:
        """Fold the rows of ``state`` ``[N, obs_dim]`` into their embodiment's statistics."""
        state = torch.as_tensor(state).reshape(-1, self.obs_dim)
        kinds = self.kinds(state)
        for kind in torch.unique(kinds).tolist():
            self.stats[kind].update(state[kinds == kind, :self.features])

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        kinds = self.kinds(state)
        mean = torch.stack([s.mean for s in self.stats])[kinds]
        std = torch.sqrt(torch.stack([s.var for s in self.stats])[kinds] + 1e-8)
        features = ((state[:, :self.features].to(torch.float64) - mean) / std).clamp(-self.clip, self.clip)
        return torch.cat([features.to(state.dtype), state[:, self.features:]], dim=-1)


class NormalizedStateEncoder(nn.Module):
    """``normalizer`` on ``obs["state"]`` (or on a bare state tensor), then ``inner`` (an encoder, or
    None: the networks read the normalised state). It has no parameters of its own."""

    def __init__(self, normalizer: EmbodimentStateNormalizer, inner: nn.Module | None = None):
        super().__init__()
        self.normalizer, self.inner = normalizer, inner
        self.out_dim = normalizer.obs_dim if inner is None else inner.out_dim

    @property
    def cameras(self) -> dict:
        """The camera fields the inner encoder reads (none without one)."""
        return dict(getattr(self.inner, "cameras", {}) or {})

    def forward(self, obs):
        if isinstance(obs, Mapping):
            obs = {**obs, "state": self.normalizer(obs["state"])}
            return obs["state"] if self.inner is None else self.inner(obs)
        state = self.normalizer(obs)
        return state if self.inner is None else self.inner({"state": state})
