"""Vision-language-action models: the π0 / π0.5 family and the small ``pi0_smollm2`` (docs/vla.md).

Our own modules on transformers' SigLIP / PaliGemma / Gemma / Llama classes, loading LeRobot's
published π0/π0.5 checkpoint folders (and openpi's PyTorch key names) from a local path, and
SmolLM2's first layers for the small family.

Names are exported lazily: importing the package (as the policy registry does, through
:mod:`.policy`) does not import transformers' model classes until a model is used.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "FAMILY_SWITCHES": "config",
    "GEMMA_VARIANTS": "config",
    "SIGLIP_SO400M": "config",
    "FamilySwitches": "config",
    "GemmaSpec": "config",
    "SiglipSpec": "config",
    "VLAArchitecture": "config",
    "VLAConfig": "config",
    "read_vla_config": "config",
    "PiZero": "model",
    "PrefixCache": "model",
    "VLAInputs": "processor",
    "VLAProcessor": "processor",
    "VLA": "vla",
    "load_vla": "vla",
    "PiZeroPolicy": "policy",
    "PiZeroFivePolicy": "policy",
    "PiZeroSmolLM2Policy": "policy",
    "LlamaSpec": "config",
    "ConvStemSpec": "config",
    "STACK_KINDS": "layers",
    "VISION_TOWERS": "vision",
    "save_vla": "save",
    "SmolVLASpec": "smollm2_vla",
    "build_pi0_smollm2": "smollm2_vla",
    "build_vla": "smollm2_vla",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)


def __dir__() -> list[str]:
    return __all__
