"""How a robot worker uses an intervention device: which device, where the reward comes from, and
where success labels go."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from infinirl.realworld.intervention.device import INTERVENTION_DEVICES, InterventionDevice
from infinirl.realworld.intervention.human_reward import REWARD_SOURCES

__all__ = ["InterventionSpec"]


@dataclass(frozen=True, kw_only=True)
class InterventionSpec:
    """``device`` / ``options``: the device (``INTERVENTION_DEVICES.get(device)(action_dim=..., **options)``).
    ``reward``: ``env`` (the env's reward; marks only label) or ``human`` (the marks are the reward,
    :mod:`~infinirl.realworld.intervention.human_reward`). ``labels_dir``: where marked episodes'
    observations are saved as success-classifier labels (None: not saved)."""

    device: str
    options: Mapping[str, Any] = field(default_factory=dict)
    reward: Literal["env", "human"] = "env"
    labels_dir: str | None = None

    def __post_init__(self) -> None:
        INTERVENTION_DEVICES.get(self.device)  # an unknown name fails listing the registered ones
        if self.reward not in REWARD_SOURCES:
            raise ValueError(f"InterventionSpec.reward must be one of {REWARD_SOURCES}, got {self.reward!r}")

    def build(self, action_dim: int) -> InterventionDevice:
        return INTERVENTION_DEVICES.get(self.device)(action_dim=action_dim, **dict(self.options))
