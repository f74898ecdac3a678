"""Registers the VLA policies (``pi0``, ``pi05``, ``pi0_smollm2``, and each one's ``_steered``
form), defined in :mod:`infinirl.models.vla.policy` and :mod:`infinirl.models.vla.steered`;
``build_policy`` imports every module of this package, so this import is their registration."""

from infinirl.models.vla.policy import PiZeroFivePolicy, PiZeroPolicy, PiZeroSmolLM2Policy
from infinirl.models.vla.steered import PiZeroFiveSteeredPolicy, PiZeroSmolLM2SteeredPolicy, PiZeroSteeredPolicy

__all__ = ["PiZeroFivePolicy", "PiZeroFiveSteeredPolicy", "PiZeroPolicy", "PiZeroSmolLM2Policy",
           "PiZeroSmolLM2SteeredPolicy", "PiZeroSteeredPolicy"]
