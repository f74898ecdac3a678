"""What an OpenVLA / OpenVLA-OFT checkpoint folder says about its model, read without the hub.

``config.json`` (``OpenVLAConfig``: ``"architectures": ["OpenVLAForActionPrediction"]``) names the
vision backbone (``vision_backbone_id`` -> timm ViT ids and image sizes), carries the Llama
``text_config``, ``n_action_bins`` and ``pad_to_multiple_of``; ``preprocessor_config.json`` holds
each backbone's pixel mean/std; ``dataset_statistics.json`` (else ``config.json``'s ``norm_stats``)
the per-dataset action/proprio statistics.

Two things are not in the folder and come from OFT's code (``prismatic/vla/constants.py``): the
*platform* (actions per chunk, action and proprio dims, bounds or q01/q99 normalisation), chosen
there from the command line and here by name (:data:`PLATFORMS`) or a :class:`Platform`; and the
sizes of the timm ViTs, named by id (:data:`VIT_SPECS`). Tiny test checkpoints override the latter
with ``vision=`` (an ``architecture.json``, see :func:`read_architecture`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

__all__ = ["ARCHITECTURE", "PLATFORMS", "VIT_SPECS", "OFTConfig", "Platform", "ViTSpec", "read_architecture",
           "read_oft_config"]

ARCHITECTURE = "OpenVLAForActionPrediction"
NORMALIZATIONS = {"bounds": ("min", "max"), "bounds_q99": ("q01", "q99")}


@dataclass(frozen=True, kw_only=True)
class ViTSpec:
    """One timm ViT of the (fused) vision backbone."""

    kind: str  # "dinov2" (class token, registers, layer scale) or "siglip" (neither)
    width: int
    depth: int
    num_heads: int
    mlp_dim: int
    patch_size: int
    image_size: int = 224
    register_tokens: int = 0

    @property
    def num_patches(self) -> int:
        return (self.image_size // self.patch_size) ** 2


@dataclass(frozen=True, kw_only=True)
class Platform:
    """OFT's per-robot constants (``NUM_ACTIONS_CHUNK``, ``ACTION_DIM``, ``PROPRIO_DIM``, normalisation).

    ``invert_gripper``: OpenVLA's data loader stored this robot's gripper as 0 = close, 1 = open (left
    unnormalised), while its env takes -1 = open, +1 = close; OFT's eval turns the last action dim ``g``
    into ``-sign(2g - 1)`` before stepping (``normalize_gripper_action`` + ``invert_gripper_action``).
    """

    chunk_size: int
    action_dim: int
    proprio_dim: int
    normalization: str = "bounds_q99"
    invert_gripper: bool = False


PLATFORMS = {
    "libero": Platform(chunk_size=8, action_dim=7, proprio_dim=8, normalization="bounds_q99", invert_gripper=True),
    "aloha": Platform(chunk_size=25, action_dim=14, proprio_dim=14, normalization="bounds"),
    "bridge": Platform(chunk_size=5, action_dim=7, proprio_dim=7, normalization="bounds_q99"),
}

_DINOV2_L = ViTSpec(kind="dinov2", width=1024, depth=24, num_heads=16, mlp_dim=4096, patch_size=14, register_tokens=4)
_SIGLIP_SO400M = ViTSpec(kind="siglip", width=1152, depth=27, num_heads=16, mlp_dim=4304, patch_size=14)
VIT_SPECS = {
    "vit_large_patch14_reg4_dinov2.lvd142m": _DINOV2_L,
    "vit_so400m_patch14_siglip_224": _SIGLIP_SO400M,
    "vit_so400m_patch14_siglip_384": _SIGLIP_SO400M,
}


@dataclass(frozen=True, kw_only=True)
class OFTConfig:
    """Everything the model and processor need, from the folder plus the platform."""

    vision: tuple[ViTSpec, ...]
    text_config: dict[str, Any]
    platform: Platform
    num_images: int = 1
    n_action_bins: int = 256
    pad_to_multiple_of: int = 64
    image_means: tuple[tuple[float, ...], ...] = ()
    image_stds: tuple[tuple[float, ...], ...] = ()
    norm_stats: dict[str, Any] = field(default_factory=dict)
    empty_token_id: int = 29871  # Llama-2's "▁": OFT appends it after "Out:", as at training time
    stop_token_id: int = 2  # "</s>", after the action tokens

    @property
    def fused(self) -> bool:
        return len(self.vision) == 2

    @property
    def image_size(self) -> int:
        return self.vision[0].image_size

    @property
    def llm_dim(self) -> int:
        return int(self.text_config["hidden_size"])

    @property
    def num_action_tokens(self) -> int:
        return self.platform.chunk_size * self.platform.action_dim

    @property
    def vocab_size(self) -> int:
        """The tokenizer's vocabulary (the LM's, less the padding rows): action tokens end here."""
        return int(self.text_config["vocab_size"]) - self.pad_to_multiple_of

    @property
    def num_patches(self) -> int:
        return self.vision[0].num_patches * self.num_images

    @property
    def max_positions(self) -> int:
        return int(self.text_config.get("max_position_embeddings", 2048))  # LlamaConfig's default


def read_architecture(path: str | Path) -> tuple[dict[str, int], ...]:
    """ViT size overrides for a checkpoint of non-published sizes: ``{"vision": [{width, depth, ...}, ...]}``
    in the folder's backbone order; fields left out (and the kinds) come from the published ViT."""
    entries = json.loads(Path(path).read_text())["vision"]
    unknown = sorted({key for entry in entries for key in entry} - set(ViTSpec.__dataclass_fields__) - {"kind"})
    if unknown:
        raise ValueError(f"{path}: unknown ViT fields {unknown}; known {sorted(ViTSpec.__dataclass_fields__)}")
    return tuple(dict(entry) for entry in entries)


def _load_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"no {path.name} in {path.parent}: an OpenVLA-OFT checkpoint folder holds {what}")
    return json.loads(path.read_text())


def _check_family(folder: Path, config: dict) -> None:
    architectures = config.get("architectures") or []
    if ARCHITECTURE in architectures and config.get("model_type") == "openvla":
        return
    found = (f"a LeRobot '{config['type']}' policy" if "type" in config else
             f"architectures={architectures} model_type={config.get('model_type')!r}")
    raise ValueError(f"{folder / 'config.json'} is not an OpenVLA/OpenVLA-OFT checkpoint ({found}); expected "
                     f"\"architectures\": [\"{ARCHITECTURE}\"]: pass the folder OFT's fine-tuning saved")


def _vision_specs(folder: Path, config: dict, vision: tuple[dict[str, int], ...] | None) -> tuple[ViTSpec, ...]:
    ids, sizes = config.get("timm_model_ids", []), config.get("image_sizes", [])
    unknown = [model_id for model_id in ids if model_id not in VIT_SPECS]
    if unknown or not ids:
        raise ValueError(f"{folder / 'config.json'}: vision backbone {config.get('vision_backbone_id')!r} "
                         f"(timm {unknown or ids}) is not supported; known ViTs: {sorted(VIT_SPECS)}")
    specs = tuple(replace(VIT_SPECS[model_id], image_size=int(size)) for model_id, size in zip(ids, sizes, strict=True))
    if vision is not None:
        if len(vision) != len(specs):
            raise ValueError(f"vision= gives {len(vision)} ViTs, {folder / 'config.json'} names {len(specs)}")
        specs = tuple(replace(spec, **override) for spec, override in zip(specs, vision, strict=True))
    if len({spec.image_size for spec in specs}) != 1:
        raise ValueError(f"{folder / 'config.json'}: backbones of different image sizes are not supported")
    return specs


def read_oft_config(folder: str | Path, *, platform: str | Platform = "libero", num_images: int = 1,
                    vision: tuple[dict[str, int], ...] | None = None) -> OFTConfig:
    """Read ``config.json``, ``preprocessor_config.json`` and the statistics of an OpenVLA(-OFT) folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such checkpoint folder")
    config = _load_json(folder / "config.json", "config.json (OpenVLAConfig)")
    _check_family(folder, config)
    if isinstance(platform, str):
        if platform not in PLATFORMS:
            raise ValueError(f"platform={platform!r}: known {sorted(PLATFORMS)}, or pass a Platform(...)")
        platform = PLATFORMS[platform]
    if platform.normalization not in NORMALIZATIONS:
        raise ValueError(f"platform normalization {platform.normalization!r}: known {sorted(NORMALIZATIONS)}")
    specs = _vision_specs(folder, config, vision)
    text = config.get("text_config") or {}
    if text.get("model_type", "llama") != "llama":
        raise ValueError(f"{folder / 'config.json'}: text_config model_type {text.get('model_type')!r}; only Llama "
                         "language models are supported")
    if num_images > 1 and len(specs) != 2:
        raise ValueError("several images per observation need the fused (DINOv2 + SigLIP) backbone, as in OFT")
    processor = _load_json(folder / "preprocessor_config.json", "preprocessor_config.json (image mean/std)")
    means, stds = processor.get("means"), processor.get("stds")
    if not means or not stds or len(means) != len(specs):
        raise ValueError(f"{folder / 'preprocessor_config.json'}: needs one 'means'/'stds' entry per backbone "
                         f"({len(specs)})")
    statistics = folder / "dataset_statistics.json"
    norm_stats = json.loads(statistics.read_text()) if statistics.is_file() else dict(config.get("norm_stats") or {})
    return OFTConfig(vision=specs, text_config=dict(text), platform=platform, num_images=num_images,
                     n_action_bins=int(config.get("n_action_bins", 256)),
                     pad_to_multiple_of=int(config.get("pad_to_multiple_of", 64)),
                     image_means=tuple(tuple(m) for m in means), image_stds=tuple(tuple(s) for s in stds),
                     norm_stats=norm_stats)
