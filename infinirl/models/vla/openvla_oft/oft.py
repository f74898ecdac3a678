"""A loaded OpenVLA-OFT checkpoint (network + processor) and :func:`load_openvla_oft`.

Folder layout (what OFT's ``vla-scripts/finetune.py`` writes, and its hub repos hold)::

    config.json                         # OpenVLAConfig, "architectures": ["OpenVLAForActionPrediction"]
    model.safetensors | model-0000k-of-0000n.safetensors + model.safetensors.index.json
    preprocessor_config.json            # PrismaticImageProcessor: per-backbone mean/std, sizes
    tokenizer files                     # Llama-2's, <PAD> = 32000
    dataset_statistics.json             # {unnorm_key: {"action": {q01, q99, min, max, mask}, "proprio": {...}}}
    action_head--<step>_checkpoint.pt   # L1 head (OFT's continuous variant)
    proprio_projector--<step>_checkpoint.pt

``configuration_prismatic.py`` / ``modeling_prismatic.py`` (the ``auto_map``) are not read: our
modules replace them. Nothing is fetched from a hub.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from infinirl.models.vla.openvla_oft.checkpoint import find_component, load_component, load_weights
from infinirl.models.vla.openvla_oft.config import OFTConfig, Platform, read_oft_config
from infinirl.models.vla.openvla_oft.model import OpenVLAOFT
from infinirl.models.vla.openvla_oft.processor import OFTProcessor, load_tokenizer

__all__ = ["HEADS", "OFTInputs", "OpenVLAOFTBundle", "load_openvla_oft"]

HEADS = ("discrete", "l1")


class OFTInputs(dict):
    """``pixel_values``, ``input_ids``, ``lengths`` and (with a proprio projector) ``proprio``."""


class OpenVLAOFTBundle(nn.Module):
    """:class:`~.model.OpenVLAOFT` and its :class:`~.processor.OFTProcessor`, moved together."""

    def __init__(self, model: OpenVLAOFT, processor: OFTProcessor, head: str):
        super().__init__()
        self.model, self.processor, self.head = model, processor, head

    @property
    def config(self) -> OFTConfig:
        return self.model.config

    def inputs(self, images: list[Any], instructions: list[str], proprio: Any = None) -> OFTInputs:
        """Raw cameras (primary first), instructions and proprio -> model inputs on the model's device."""
        device = self.model.projector.fc1.weight.device
        pixel_values = self.processor.pixel_values(images).to(device)
        if pixel_values.shape[0] != len(instructions):
            raise ValueError(f"{pixel_values.shape[0]} images but {len(instructions)} instructions")
        input_ids, lengths = self.processor.tokenize(instructions, device=device)
        inputs = OFTInputs(pixel_values=pixel_values, input_ids=input_ids, lengths=lengths)
        if self.model.proprio_projector is not None:
            if proprio is None:
                raise ValueError("this checkpoint has a proprio projector: pass proprio= (raw, env units)")
            inputs["proprio"] = self.processor.proprio(proprio).to(device)
        return inputs

    def action_states(self, inputs: OFTInputs):
        return self.model.action_states(inputs["pixel_values"], inputs["input_ids"], inputs["lengths"],
                                        inputs.get("proprio"))

    @torch.no_grad()
    def predict_action_chunk(self, images: list[Any], instructions: list[str], proprio: Any = None) -> torch.Tensor:
        """Env-unit actions ``[B, chunk, action_dim]`` (float64), as OFT's ``predict_action``: the L1
        head's regression, or the arg-max token over the whole vocabulary mapped to its bin."""
        states = self.action_states(self.inputs(images, instructions, proprio))
        if self.head == "l1":
            normalized = self.model.regress(states.hidden)
        else:
            tokens = self.model.action_logits(states.hidden, full_vocab=True).argmax(-1)
            normalized = self.model.token_actions(tokens)
        return self.processor.actions_out(normalized)


def load_openvla_oft(folder: str | Path, *, head: str = "l1", unnorm_key: str | None = None,
                     platform: str | Platform = "libero", num_images: int = 1, use_proprio: bool | None = None,
                     vision: tuple[dict[str, int], ...] | None = None, tokenizer: Any = None, resize: bool = False,
                     device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                     attention: str = "sdpa") -> OpenVLAOFTBundle:
    """Load an OpenVLA-OFT folder (module docstring) with no hub access.

    Args:
        head: ``"l1"`` (OFT's regression head, needs ``action_head--*.pt``) or ``"discrete"`` (256-bin
            action tokens from the LM head; OpenVLA's own head).
        unnorm_key: the dataset whose statistics (un)normalise (required when there are several).
        platform: OFT's constants: ``"libero"``, ``"aloha"``, ``"bridge"`` or a :class:`Platform`.
        num_images: images per observation (primary + wrist cameras), as fine-tuned.
        use_proprio: feed the proprio token (default: when ``proprio_projector--*.pt`` is present).
        vision: ViT sizes for checkpoints of non-published sizes (:func:`~.config.read_architecture`).
        tokenizer: a tokenizer object or folder, when the folder's tokenizer files are missing.
        resize: resize camera images of another size (bicubic) instead of refusing them.
    """
    if head not in HEADS:
        raise ValueError(f"head={head!r}: one of {HEADS}")
    folder = Path(folder)
    config = read_oft_config(folder, platform=platform, num_images=num_images, vision=vision)
    head_file = find_component(folder, "action_head")
    proprio_file = find_component(folder, "proprio_projector")
    if head == "l1" and head_file is None:
        raise FileNotFoundError(f"no action_head--<step>_checkpoint.pt in {folder}: the L1 head is saved beside "
                                "the VLA by OFT's fine-tuning; use head='discrete' for a token-only checkpoint")
    proprio = proprio_file is not None if use_proprio is None else use_proprio
    if proprio and proprio_file is None:
        raise FileNotFoundError(f"use_proprio=True but no proprio_projector--<step>_checkpoint.pt in {folder}")
    processor = OFTProcessor(config, load_tokenizer(folder, tokenizer), unnorm_key=unnorm_key, proprio=proprio,
                             resize=resize, source=str(folder / "dataset_statistics.json"))
    model = OpenVLAOFT(config, l1_head=head == "l1", proprio=proprio, attention=attention).to(dtype=dtype)
    load_weights(model, folder)
    if model.action_head is not None:
        load_component(model.action_head, head_file, action_head=True)
    if model.proprio_projector is not None:
        load_component(model.proprio_projector, proprio_file, action_head=False)
    bundle = OpenVLAOFTBundle(model, processor, head).to(device)
    bundle.eval()
    return bundle
