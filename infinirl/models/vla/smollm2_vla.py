"""``pi0_smollm2``: a small VLA of π0's design whose language model is SmolLM2-135M's first layers.

A VLA that trains on a CPU, from the model this project embeds (:mod:`infinirl.models.smollm2`),
with nothing downloaded:

* prefix: each camera through a small conv stem (:class:`~.vision.ConvStem`, 16 tokens for a
  64 px image, trained from scratch), then the instruction's SmolLM2 tokens; bidirectional;
* language model: SmolLM2's token embedding, its first ``language_layers`` decoder layers and its
  final norm (a Llama: RMSNorm with plain weight, SiLU MLP, 9 heads / 3 kv heads of 64, rope
  theta 1e5). SmolVLA truncates its language model the same way: the upper layers specialise in
  next-token prediction, which an action model does not need;
* action expert: as many Llama layers, narrower (``expert_width``) but with the same heads, since
  it attends jointly with the language model in every layer (:func:`~.layers.mixture_forward`);
* π0's suffix and flow matching: one state token, the noisy action chunk mixed with the flow time.

:func:`build_pi0_smollm2` makes one (SmolLM2's weights where they exist, the rest initialised
randomly); :func:`~.save.save_vla` writes it as a checkpoint folder, which
:func:`~.vla.load_vla` and the ``pi0_smollm2`` policy read back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open

from infinirl.models.vla.config import ConvStemSpec, LlamaSpec, VLAArchitecture, VLAConfig
from infinirl.models.vla.model import PiZero
from infinirl.models.vla.normalize import Normalizer
from infinirl.models.vla.processor import ACTION, STATE, VLAProcessor, load_tokenizer
from infinirl.models.vla.vla import VLA

__all__ = ["FAMILY", "SMOLLM2_135M", "SMOLLM2_VOCAB", "SmolVLASpec", "build_pi0_smollm2", "build_vla",
           "load_smollm2_layers", "pi0_smollm2_config", "smollm2_folder"]

FAMILY = "pi0_smollm2"
SMOLLM2_135M = LlamaSpec(width=576, depth=30, mlp_dim=1536, num_heads=9, num_kv_heads=3, head_dim=64,
                         rope_theta=100_000.0, rms_norm_eps=1e-5)
SMOLLM2_VOCAB = 49152


@dataclass(kw_only=True, frozen=True)
class SmolVLASpec:
    """The sizes and options of a ``pi0_smollm2`` model (the language model's are SmolLM2's)."""

    language_layers: int = 4
    """SmolLM2 decoder layers kept (of 30); the action expert has as many."""
    expert_width: int = 288
    """Half SmolLM2's width; a multiple of its 9 heads (transformers' Llama requires it) and even."""
    expert_mlp_dim: int = 768
    vision: ConvStemSpec = field(default_factory=ConvStemSpec)
    image_size: int = 64
    chunk_size: int = 8
    n_action_steps: int = 8
    num_inference_steps: int = 10
    tokenizer_max_length: int = 16
    """Instruction tokens at most (a longer instruction is refused); MetaWorld's fit in 12."""

    def __post_init__(self) -> None:
        if not 1 <= self.language_layers <= SMOLLM2_135M.depth:
            raise ValueError(f"language_layers={self.language_layers}: SmolLM2-135M has {SMOLLM2_135M.depth} "
                             "layers; keep between 1 and all of them")
        if self.expert_width % (2 * SMOLLM2_135M.num_heads):
            raise ValueError(f"expert_width={self.expert_width} must be a multiple of {2 * SMOLLM2_135M.num_heads}: "
                             f"of SmolLM2's {SMOLLM2_135M.num_heads} heads, and even (the flow-time embedding)")
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(f"n_action_steps={self.n_action_steps} must be in [1, chunk_size={self.chunk_size}]")


def pi0_smollm2_config(spec: SmolVLASpec, *, camera_keys: tuple[str, ...], state_dim: int, action_dim: int,
                       instructions: dict[str, str] | None = None) -> VLAConfig:
    """The :class:`VLAConfig` of a ``pi0_smollm2`` model (no padding: the data's own dims)."""
    vlm = LlamaSpec(**{**SMOLLM2_135M.__dict__, "depth": spec.language_layers})
    expert = LlamaSpec(**{**vlm.__dict__, "width": spec.expert_width, "mlp_dim": spec.expert_mlp_dim})
    architecture = VLAArchitecture(vlm=vlm, expert=expert, vision=spec.vision, vocab_size=SMOLLM2_VOCAB)
    return VLAConfig(family=FAMILY, architecture=architecture, camera_keys=tuple(camera_keys), state_dim=state_dim,
                     action_dim=action_dim, chunk_size=spec.chunk_size, n_action_steps=spec.n_action_steps,
                     max_state_dim=state_dim, max_action_dim=action_dim,
                     num_inference_steps=spec.num_inference_steps,
                     image_resolution=(spec.image_size, spec.image_size),
                     tokenizer_max_length=spec.tokenizer_max_length, instructions=dict(instructions or {}))


def build_vla(config: VLAConfig, stats: dict[str, dict[str, Any]], tokenizer: Any) -> VLA:
    """A randomly initialised VLA of ``config`` with normalisation ``stats`` (``{"observation.state":
    {"mean": ..., "std": ...}, "action": {...}}``, the statistics ``config.normalization`` needs)."""
    modes = {STATE: config.normalization.get("STATE", "IDENTITY"),
             ACTION: config.normalization.get("ACTION", "IDENTITY")}
    stats = {feature: {name: torch.as_tensor(value, dtype=torch.float32) for name, value in values.items()}
             for feature, values in stats.items()}
    input_norm = Normalizer(modes, stats)
    output_norm = Normalizer({ACTION: modes[ACTION]}, stats)
    processor = VLAProcessor(config, input_norm, output_norm, tokenizer=load_tokenizer(tokenizer))
    return VLA(PiZero(config), processor)


def smollm2_folder() -> Path:
    """The embedded SmolLM2-135M-Instruct as a safetensors folder (converted on first use)."""
    from infinirl.models.smollm2 import ensure_converted

    return ensure_converted()


def load_smollm2_layers(model: PiZero, folder: str | Path) -> None:
    """Copy SmolLM2's token embedding, its first ``depth`` layers and its final norm into ``model.vlm``."""
    path = Path(folder) / "model.safetensors"
    if not path.is_file():
        raise FileNotFoundError(f"no model.safetensors in {folder}: pass the SmolLM2 folder "
                                "(infinirl.models.smollm2.ensure_converted() makes it)")
    targets = {name: tensor for name, tensor in model.vlm.state_dict().items()}
    with safe_open(str(path), framework="pt") as handle:
        available = set(handle.keys())
        loaded = {}
        for name, tensor in targets.items():
            key = f"model.{name}"
            if key not in available:
                raise ValueError(f"{path}: no {key!r}: is this SmolLM2-135M (a Llama with >= "
                                 f"{model.vlm.spec.depth} layers)?")
            value = handle.get_tensor(key)
            if tuple(value.shape) != tuple(tensor.shape):
                raise ValueError(f"{path}: {key!r} has shape {list(value.shape)}, the model expects "
                                 f"{list(tensor.shape)}: is this SmolLM2-135M?")
            loaded[name] = value.to(tensor.dtype)
    model.vlm.load_state_dict(loaded, strict=True)


def build_pi0_smollm2(spec: SmolVLASpec, *, camera_keys: tuple[str, ...], state_dim: int, action_dim: int,
                      stats: dict[str, dict[str, Any]], instructions: dict[str, str] | None = None,
                      smollm2: str | Path | None = None, seed: int = 0) -> VLA:
    """A new ``pi0_smollm2`` VLA: SmolLM2's first ``spec.language_layers`` layers, embedding,
    final norm and tokenizer from ``smollm2`` (default: the embedded model), everything else
    initialised from ``seed``."""
    folder = Path(smollm2) if smollm2 is not None else smollm2_folder()
    config = pi0_smollm2_config(spec, camera_keys=camera_keys, state_dim=state_dim, action_dim=action_dim,
                                instructions=instructions)
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        vla = build_vla(config, stats, tokenizer=folder)
    load_smollm2_layers(vla.model, folder)
    return vla
