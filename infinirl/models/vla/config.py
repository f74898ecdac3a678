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
from typing import Any, ClassVar

from infinirl.registry import Registry

__all__ = [
    "FAMILY_SWITCHES",
    "GEMMA_VARIANTS",
    "NORMALIZATION_MODES",
    "PALIGEMMA_VOCAB",
    "SIGLIP_SO400M",
    "STACK_SPECS",
    "VISION_SPECS",
    "ConvStemSpec",
    "FamilySwitches",
    "GemmaSpec",
    "LlamaSpec",
    "SiglipSpec",
    "VLAArchitecture",
    "VLAConfig",
    "read_vla_config",
    "spec_from_dict",
    "spec_to_dict",
]

PALIGEMMA_VOCAB = 257152
NORMALIZATION_MODES = ("IDENTITY", "MEAN_STD", "MIN_MAX", "QUANTILES", "QUANTILE10")
DEFAULT_NORMALIZATION = {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"}


@dataclass(kw_only=True, frozen=True)
class GemmaSpec:
    """Sizes of one Gemma stack (openpi's ``gemma.Config``)."""

    kind: ClassVar[str] = "gemma"
    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    num_kv_heads: int
    head_dim: int


@dataclass(kw_only=True, frozen=True)
class LlamaSpec:
    """Sizes of one Llama stack (SmolLM2's layout: plain RMSNorm, SiLU MLP, grouped-query attention)."""

    kind: ClassVar[str] = "llama"
    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    num_kv_heads: int
    head_dim: int
    rope_theta: float = 10_000.0
    rms_norm_eps: float = 1e-5


@dataclass(kw_only=True, frozen=True)
class SiglipSpec:
    """Sizes of the SigLIP vision tower (its image size is the checkpoint's ``image_resolution``)."""

    kind: ClassVar[str] = "siglip"
    hidden_size: int
    intermediate_size: int
    num_hidden_layers: int
    num_attention_heads: int
    patch_size: int


@dataclass(kw_only=True, frozen=True)
class ConvStemSpec:
    """A small convolutional image encoder (:class:`~.vision.ConvStem`): one stride-2 stage per
    entry of ``channels`` (3x3 conv, GroupNorm, SiLU), the last feature map's cells as tokens."""

    kind: ClassVar[str] = "conv"
    channels: tuple[int, ...] = (32, 64, 128, 256)
    groups: int = 8

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        if not self.channels or any(c % self.groups for c in self.channels):
            raise ValueError(f"ConvStemSpec.channels {list(self.channels)}: give at least one stage, each a "
                             f"multiple of groups={self.groups} (GroupNorm)")


STACK_SPECS: Registry[type] = Registry("decoder stack kind")
STACK_SPECS.add("gemma", GemmaSpec)
STACK_SPECS.add("llama", LlamaSpec)
VISION_SPECS: Registry[type] = Registry("vision encoder kind")
VISION_SPECS.add("siglip", SiglipSpec)
VISION_SPECS.add("conv", ConvStemSpec)


def spec_from_dict(registry: Registry[type], data: dict[str, Any], default_kind: str):
    """A spec from its JSON form: ``{"kind": ..., sizes...}`` (no ``kind``: ``default_kind``)."""
    data = dict(data)
    return registry.get(data.pop("kind", default_kind))(**data)


def spec_to_dict(spec) -> dict[str, Any]:
    """The JSON form :func:`spec_from_dict` reads (lists for tuples)."""
    return {"kind": spec.kind, **{k: list(v) if isinstance(v, tuple) else v for k, v in asdict(spec).items()}}


GEMMA_VARIANTS: Registry[GemmaSpec] = Registry("gemma variant")
GEMMA_VARIANTS.add("gemma_300m", GemmaSpec(width=1024, depth=18, mlp_dim=4096, num_heads=8, num_kv_heads=1,
                                           head_dim=256))
GEMMA_VARIANTS.add("gemma_2b", GemmaSpec(width=2048, depth=18, mlp_dim=16_384, num_heads=8, num_kv_heads=1,
                                         head_dim=256))
SIGLIP_SO400M = SiglipSpec(hidden_size=1152, intermediate_size=4304, num_hidden_layers=27, num_attention_heads=16,
                           patch_size=14)


@dataclass(kw_only=True, frozen=True)
class VLAArchitecture:
    """Every size the weights depend on: the VLM and expert stacks (Gemma or Llama), the vision
    encoder (SigLIP or a conv stem), the vocabulary."""

    vlm: GemmaSpec | LlamaSpec
    expert: GemmaSpec | LlamaSpec
    vision: SiglipSpec | ConvStemSpec = SIGLIP_SO400M
    vocab_size: int = PALIGEMMA_VOCAB

    def __post_init__(self) -> None:
        heads = [(s.num_heads, s.num_kv_heads, s.head_dim) for s in (self.vlm, self.expert)]
        if heads[0] != heads[1]:
            raise ValueError(
                f"the VLM and the action expert attend jointly, so they need the same heads, kv heads and head_dim; "
                f"got {'x'.join(map(str, heads[0]))} and {'x'.join(map(str, heads[1]))}"
            )
        if self.vlm.depth != self.expert.depth:
            raise ValueError(f"the VLM and the action expert need the same depth, got {self.vlm.depth} and "
                             f"{self.expert.depth}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VLAArchitecture:
        """From ``{"vlm": {...}, "expert": {...}, "vision": {...}, "vocab_size": n}``; each spec may
        name its ``kind`` (stacks: ``gemma``, the default, or ``llama``; vision: ``siglip``, the
        default, or ``conv``)."""
        return cls(vlm=spec_from_dict(STACK_SPECS, data["vlm"], "gemma"),
                   expert=spec_from_dict(STACK_SPECS, data["expert"], "gemma"),
                   vision=spec_from_dict(VISION_SPECS, data.get("vision", asdict(SIGLIP_SO400M)), "siglip"),
                   vocab_size=int(data.get("vocab_size", PALIGEMMA_VOCAB)))

    def to_dict(self) -> dict[str, Any]:
        return {"vlm": spec_to_dict(self.vlm), "expert": spec_to_dict(self.expert),
                "vision": spec_to_dict(self.vision), "vocab_size": self.vocab_size}

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
# π0's design on SmolLM2's first layers (infinirl.models.vla.smollm2_vla): π0's switches, its own sizes.
FAMILY_SWITCHES.add("pi0_smollm2", FamilySwitches(discrete_state=False, adarms_time=False))


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
    instructions: dict[str, str] = field(default_factory=dict)
    """An env's instruction -> the wording the model was trained with (e.g. ``"reach"`` ->
    ``"reach a goal position"``); an instruction not listed is used as it is."""

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
    if architecture is None and "architecture" in raw:
        architecture = VLAArchitecture.from_dict(raw["architecture"])
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
                     instructions=dict(raw.get("instructions") or {}), **options)
