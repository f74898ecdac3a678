"""Registers the VLA policies (``pi0``, ``pi05``, ``pi0_smollm2``, and each one's ``_steered`` and
``_residual`` forms), defined in :mod:`infinirl.models.vla.policy`, :mod:`infinirl.models.vla.steered`
and :mod:`infinirl.models.vla.residual`; ``build_policy`` imports every module of this package, so
this import is their registration."""

from infinirl.models.vla.policy import PiZeroFivePolicy, PiZeroPolicy, PiZeroSmolLM2Policy
from infinirl.models.vla.residual import PiZeroFiveResidualPolicy, PiZeroResidualPolicy, PiZeroSmolLM2ResidualPolicy
from infinirl.models.vla.steered import PiZeroFiveSteeredPolicy, PiZeroSmolLM2SteeredPolicy, PiZeroSteeredPolicy

__all__ = ["PiZeroFivePolicy", "PiZeroFiveResidualPolicy", "PiZeroFiveSteeredPolicy", "PiZeroPolicy",
           "PiZeroResidualPolicy", "PiZeroSmolLM2Policy", "PiZeroSmolLM2ResidualPolicy", "PiZeroSmolLM2SteeredPolicy",
           "PiZeroSteeredPolicy"]
