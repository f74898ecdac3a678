"""Vision-language-action models: the π0 / π0.5 family (docs/vla.md).

Our own modules on transformers' SigLIP / PaliGemma / Gemma classes, loading LeRobot's published
π0/π0.5 checkpoint folders (and openpi's PyTorch key names) from a local path.
"""

from infinirl.models.vla.config import (
    FAMILY_SWITCHES,
    GEMMA_VARIANTS,
    SIGLIP_SO400M,
    FamilySwitches,
    GemmaSpec,
    SiglipSpec,
    VLAArchitecture,
    VLAConfig,
    read_vla_config,
)
from infinirl.models.vla.model import PiZero, PrefixCache
from infinirl.models.vla.processor import VLAInputs, VLAProcessor
from infinirl.models.vla.vla import VLA, load_vla

__all__ = [
    "FAMILY_SWITCHES",
    "GEMMA_VARIANTS",
    "SIGLIP_SO400M",
    "VLA",
    "FamilySwitches",
    "GemmaSpec",
    "PiZero",
    "PrefixCache",
    "SiglipSpec",
    "VLAArchitecture",
    "VLAConfig",
    "VLAInputs",
    "VLAProcessor",
    "load_vla",
    "read_vla_config",
]
