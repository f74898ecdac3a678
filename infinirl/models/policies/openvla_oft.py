"""Registers the OpenVLA-OFT policy (``openvla_oft``), defined in :mod:`infinirl.models.vla.openvla_oft.policy`;
``build_policy`` imports every module of this package, so this import is its registration."""

from infinirl.models.vla.openvla_oft.policy import OpenVLAOFTPolicy

__all__ = ["OpenVLAOFTPolicy"]
