"""Typed specs of the π0 / π0.5 family, and the reader of LeRobot's ``config.json``.

A checkpoint's ``config.json`` (LeRobot's ``PI0Config`` / ``PI05Config``, saved by draccus) names
its Gemma sizes by variant (``paligemma_variant: gemma_2b``, ``action_expert_variant:
gemma_300m``); :data:`GEMMA_VARIANTS` maps those names to sizes. The SigLIP tower and the
vocabulary are not in the file: every published checkpoint uses SigLIP-so400m/14 and PaliGemma's
257152-token vocabulary (:data:`SIGLIP_SO400M`, :data:`PALIGEMMA_VOCAB`). A checkpoint of other
sizes (the tests' tiny ones) is loaded by passing its :class:`VLAArchitecture` explicitly.

π0.5 differs from π0 by two switches, not by separate code (:data:`FAMILY_SWITCHES`):

* ``discrete_state``: the normalised state is written into the prompt as 256-bin integers
  (``"Task: ..., State: 12 200 ...;\\nAction: "``) instead of entering the action expert through
  ``state_proj`` as one extra suffix token;
* ``adarms_time``: the flow time conditions every expert RMSNorm (adaRMS: scale, shift and a
  residual gate from a ``dense`` layer) through ``time_mlp_in/out``, instead of being concatenated
  with each noisy action and mixed by ``action_time_mlp_in/out``.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from infinirl.registry import Registry

__all__ = [
    "FAMILY_SWITCHES",
    "GEMMA_VARIANTS",
    "NORMALIZATION_MODES",
    "PALIGEMMA_VOCAB",
    "SIGLIP_SO400M",
    "FamilySwitches",
    "GemmaSpec",
    "SiglipSpec",
    "VLAArchitecture",
    "VLAConfig",
    "read_vla_config",
]

PALIGEMMA_VOCAB = 257152
NORMALIZATION_MODES = ("IDENTITY", "MEAN_STD", "MIN_MAX", "QUANTILES", "QUANTILE10")
DEFAULT_NORMALIZATION = {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"}


@dataclass(kw_only=True, frozen=True)
class GemmaSpec:
    """Sizes of one Gemma stack (openpi's ``gemma.Config``)."""

    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    num_kv_heads: int
    head_dim: int


@dataclass(kw_only=True, frozen=True)
class SiglipSpec:
    """Sizes of the SigLIP vision tower (its image size is the checkpoint's ``image_resolution``)."""

    hidden_size: int
    intermediate_size: int
    num_hidden_layers: int
    num_attention_heads: int
    patch_size: int


GEMMA_VARIANTS: Registry[GemmaSpec] = Registry("gemma variant")
GEMMA_VARIANTS.add("gemma_300m", GemmaSpec(width=1024, depth=18, mlp_dim=4096, num_heads=8, num_kv_heads=1,
                                           head_dim=256))
GEMMA_VARIANTS.add("gemma_2b", GemmaSpec(width=2048, depth=18, mlp_dim=16_384, num_heads=8, num_kv_heads=1,
                                         head_dim=256))
SIGLIP_SO400M = SiglipSpec(hidden_size=1152, intermediate_size=4304, num_hidden_layers=27, num_attention_heads=16,
                           patch_size=14)


@dataclass(kw_only=True, frozen=True)
class VLAArchitecture:
    """Every size the weights depend on: the VLM and expert Gemmas, SigLIP, the vocabulary."""

    vlm: GemmaSpec
    expert: GemmaSpec
    vision: SiglipSpec = SIGLIP_SO400M
    vocab_size: int = PALIGEMMA_VOCAB

    def __post_init__(self) -> None:
        if (self.vlm.num_heads, self.vlm.head_dim) != (self.expert.num_heads, self.expert.head_dim):
            raise ValueError(
                f"the VLM and the action expert attend jointly, so they need the same heads and head_dim; got "
                f"{self.vlm.num_heads}x{self.vlm.head_dim} and {self.expert.num_heads}x{self.expert.head_dim}"
            )
        if self.vlm.depth != self.expert.depth:
            raise ValueError(f"the VLM and the action expert need the same depth, got {self.vlm.depth} and "
                             f"{self.expert.depth}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VLAArchitecture:
        """From ``{"vlm": {...}, "expert": {...}, "vision": {...}, "vocab_size": n}``."""
        return cls(vlm=GemmaSpec(**data["vlm"]), expert=GemmaSpec(**data["expert"]),
                   vision=SiglipSpec(**data.get("vision", asdict(SIGLIP_SO400M))),
                   vocab_size=int(data.get("vocab_size", PALIGEMMA_VOCAB)))

    @classmethod
    def from_json(cls, path: str | Path) -> VLAArchitecture:
        return cls.from_dict(json.loads(Path(path).read_text()))


@dataclass(kw_only=True, frozen=True)
class FamilySwitches:
    """What sets a family apart (module docstring)."""

    discrete_state: bool
    adarms_time: bool


FAMILY_SWITCHES: Registry[FamilySwitches] = Registry("VLA family")
FAMILY_SWITCHES.add("pi0", FamilySwitches(discrete_state=False, adarms_time=False))
FAMILY_SWITCHES.add("pi05", FamilySwitches(discrete_state=True, adarms_time=True))


@dataclass(kw_only=True)
class VLAConfig:
    """What the model and its processor need from a checkpoint's ``config.json``."""

    family: str
    architecture: VLAArchitecture
    camera_keys: tuple[str, ...]
    state_dim: int
    action_dim: int
    chunk_size: int = 50
    n_action_steps: int = 50
    max_state_dim: int = 32
    max_action_dim: int = 32
    num_inference_steps: int = 10
    time_sampling_beta_alpha: float = 1.5
    time_sampling_beta_beta: float = 1.0
    time_sampling_scale: float = 0.999
    time_sampling_offset: float = 0.001
    min_period: float = 4e-3
    max_period: float = 4.0
    image_resolution: tuple[int, int] = (224, 224)
    tokenizer_max_length: int = 48
    normalization: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_NORMALIZATION))

    def __post_init__(self) -> None:
        FAMILY_SWITCHES.get(self.family)
        if self.image_resolution[0] != self.image_resolution[1]:
            raise ValueError(f"image_resolution must be square (SigLIP's), got {tuple(self.image_resolution)}")
        if self.state_dim > self.max_state_dim or self.action_dim > self.max_action_dim:
            raise ValueError(f"state/action dims {self.state_dim}/{self.action_dim} exceed max_state_dim/"
                             f"max_action_dim {self.max_state_dim}/{self.max_action_dim}")
        if not self.camera_keys:
            raise ValueError("a VLA needs at least one camera (an input feature of type VISUAL)")
        for kind, mode in self.normalization.items():
            if mode not in NORMALIZATION_MODES:
                raise ValueError(f"normalization {kind}: {mode!r} is not one of {NORMALIZATION_MODES}")

    @property
    def switches(self) -> FamilySwitches:
        return FAMILY_SWITCHES.get(self.family)


LEROBOT_FIELDS = ("chunk_size", "n_action_steps", "max_state_dim", "max_action_dim", "num_inference_steps",
                  "time_sampling_beta_alpha", "time_sampling_beta_beta", "time_sampling_scale",
                  "time_sampling_offset", "min_period", "max_period", "tokenizer_max_length")


def read_vla_config(folder: str | Path, family: str | None = None,
                    architecture: VLAArchitecture | None = None) -> VLAConfig:
    """:class:`VLAConfig` from a LeRobot π0/π0.5 checkpoint folder's ``config.json``.

    ``family`` (``"pi0"``/``"pi05"``), when given, must be the checkpoint's; ``architecture``
    replaces the sizes that the variant names in the file stand for.
    """
    path = Path(folder) / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"no config.json in {folder}: a π0/π0.5 checkpoint folder holds LeRobot's "
                                "config.json, model.safetensors and policy_preprocessor.json")
    raw = json.loads(path.read_text())
    kind = raw.get("type")
    if kind is None:
        hint = f" (it is a transformers '{raw['model_type']}' config)" if "model_type" in raw else ""
        raise ValueError(f"{path} is not a LeRobot policy config: it has no 'type'{hint}; "
                         f"load_vla reads LeRobot π0/π0.5 checkpoints (type 'pi0' or 'pi05')")
    if kind not in FAMILY_SWITCHES:
        raise ValueError(f"{path} is a LeRobot '{kind}' policy; load_vla reads type "
                         f"{' or '.join(repr(n) for n in FAMILY_SWITCHES.names())}")
    if family is not None and kind != family:
        raise ValueError(f"{path} is a '{kind}' checkpoint, not '{family}': load it as family='{kind}'")
    if architecture is None:
        architecture = VLAArchitecture(vlm=GEMMA_VARIANTS.get(raw.get("paligemma_variant", "gemma_2b")),
                                       expert=GEMMA_VARIANTS.get(raw.get("action_expert_variant", "gemma_300m")))
    inputs = raw.get("input_features") or {}
    cameras = [key for key, feature in inputs.items() if feature.get("type") == "VISUAL"]
    cameras += [key for i in range(int(raw.get("empty_cameras", 0)))
                if (key := f"observation.images.empty_camera_{i}") not in cameras]
    state = inputs.get("observation.state")
    action = (raw.get("output_features") or {}).get("action")
    if action is None:
        raise ValueError(f"{path} has no output feature 'action': cannot tell the action dims")
    options = {name: raw[name] for name in LEROBOT_FIELDS if name in raw}
    return VLAConfig(family=kind, architecture=architecture, camera_keys=tuple(cameras),
                     state_dim=int(state["shape"][0]) if state else int(raw.get("max_state_dim", 32)),
                     action_dim=int(action["shape"][0]),
                     image_resolution=tuple(raw.get("image_resolution", (224, 224))),
                     normalization=dict(raw.get("normalization_mapping") or DEFAULT_NORMALIZATION),
                     **options)
