"""Registers the VLA policies (``pi0``, ``pi05``, ``pi0_smollm2``), defined in
:mod:`infinirl.models.vla.policy`; ``build_policy`` imports every module of this package, so this
import is their registration."""

from infinirl.models.vla.policy import PiZeroFivePolicy, PiZeroPolicy, PiZeroSmolLM2Policy

__all__ = ["PiZeroFivePolicy", "PiZeroPolicy", "PiZeroSmolLM2Policy"]
