"""The OpenVLA / OpenVLA-OFT family (docs/vla.md, "OpenVLA-OFT family").

Our modules on transformers' Llama, DINOv2-with-registers and SigLIP layers, loading the published
OpenVLA-OFT folders (``OpenVLAForActionPrediction`` + OFT's head files) from a local path.
Names are exported lazily, so the policy registry's import does not load transformers' models.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "PLATFORMS": "config",
    "VIT_SPECS": "config",
    "OFTConfig": "config",
    "Platform": "config",
    "ViTSpec": "config",
    "read_architecture": "config",
    "read_oft_config": "config",
    "OpenVLAOFT": "model",
    "bin_centers": "model",
    "OFTProcessor": "processor",
    "OpenVLAOFTBundle": "oft",
    "load_openvla_oft": "oft",
    "OpenVLAOFTPolicy": "policy",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)


def __dir__() -> list[str]:
    return __all__
