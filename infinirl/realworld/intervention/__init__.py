"""Human interventions: devices through which a person takes over a learning robot (docs/realworld.md).

Importing the package registers the built-in devices (``keyboard``, ``gamepad``, ``web``,
``simulated_human``) in :data:`INTERVENTION_DEVICES`.
"""

from infinirl.realworld.intervention import gamepad, keyboard, simulated_human, web  # noqa: F401 - registers devices
from infinirl.realworld.intervention.device import EPISODE_MARKS, INTERVENTION_DEVICES, HumanInput, InterventionDevice

__all__ = ["EPISODE_MARKS", "INTERVENTION_DEVICES", "HumanInput", "InterventionDevice"]
