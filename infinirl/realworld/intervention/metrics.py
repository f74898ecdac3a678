"""How much the human did: per-episode intervention counts and their rates over many episodes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["InterventionStats", "intervention_metrics", "intervention_stats"]


@dataclass(frozen=True, kw_only=True)
class InterventionStats:
    """Of one episode: its steps, the steps the human acted, and how many times the human took over
    (a run of consecutive intervened steps is one take-over)."""

    steps: int
    intervened_steps: int
    takeovers: int

    @property
    def rate(self) -> float:
        return self.intervened_steps / self.steps if self.steps else 0.0


def intervention_stats(intervened: np.ndarray) -> InterventionStats:
    """Stats of one episode from its per-step ``intervened`` flags (0/1)."""
    flags = np.asarray(intervened).reshape(-1) != 0
    starts = flags & ~np.concatenate([[False], flags[:-1]])
    return InterventionStats(steps=int(len(flags)), intervened_steps=int(flags.sum()), takeovers=int(starts.sum()))


def intervention_metrics(episodes: Sequence[InterventionStats], prefix: str = "intervention") -> dict[str, float]:
    """Over a batch of episodes: ``rate`` (intervened steps / steps), ``episode_rate`` (episodes with
    a take-over / episodes), ``takeovers_per_episode`` and ``steps`` (intervened steps). Empty: {}."""
    if not episodes:
        return {}
    steps = sum(e.steps for e in episodes)
    intervened = sum(e.intervened_steps for e in episodes)
    return {f"{prefix}/rate": intervened / steps if steps else 0.0,
            f"{prefix}/episode_rate": float(np.mean([e.takeovers > 0 for e in episodes])),
            f"{prefix}/takeovers_per_episode": float(np.mean([e.takeovers for e in episodes])),
            f"{prefix}/steps": float(intervened)}
