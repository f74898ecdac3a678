"""Human interventions: devices through which a person takes over a learning robot (docs/realworld.md)."""

from infinirl.realworld.intervention.device import EPISODE_MARKS, INTERVENTION_DEVICES, HumanInput, InterventionDevice

__all__ = ["EPISODE_MARKS", "INTERVENTION_DEVICES", "HumanInput", "InterventionDevice"]
