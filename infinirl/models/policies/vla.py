"""Registers the π0 / π0.5 policies (``pi0``, ``pi05``), defined in :mod:`infinirl.models.vla.policy`;
``build_policy`` imports every module of this package, so this import is their registration."""

from infinirl.models.vla.policy import PiZeroFivePolicy, PiZeroPolicy

__all__ = ["PiZeroFivePolicy", "PiZeroPolicy"]
