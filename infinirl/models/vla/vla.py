"""A loaded π0/π0.5 checkpoint: network + processor, and :func:`load_vla` to read one from a folder.

Folder layout (what LeRobot's ``policy.save_pretrained`` + ``preprocessor/postprocessor
.save_pretrained`` write, and what its hub repos hold)::

    config.json                                   # PI0Config / PI05Config ("type": "pi0" | "pi05")
    model.safetensors                             # LeRobot (or openpi PyTorch) key names
    policy_preprocessor.json                      # steps; the normalizer_processor step names:
    policy_preprocessor_step_<i>_normalizer_processor.safetensors
    policy_postprocessor.json                     # the unnormalizer_processor step names:
    policy_postprocessor_step_<i>_unnormalizer_processor.safetensors

The tokenizer (PaliGemma's SentencePiece, ``google/paligemma-3b-pt-224``) is not in LeRobot's
folders: pass its local folder (or a tokenizer object) as ``tokenizer=``; a ``tokenizer/``
sub-folder of the checkpoint is used when present. Nothing is fetched from a hub.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

from infinirl.models.vla.checkpoint import load_weights
from infinirl.models.vla.config import VLAArchitecture, VLAConfig, read_vla_config
from infinirl.models.vla.model import PiZero
from infinirl.models.vla.normalize import read_normalizer
from infinirl.models.vla.processor import ACTION, STATE, VLAInputs, VLAProcessor

__all__ = ["VLA", "load_processor_stats", "load_vla"]


class VLA(nn.Module):
    """:class:`~.model.PiZero` and its :class:`~.processor.VLAProcessor`, moved and saved together."""

    def __init__(self, model: PiZero, processor: VLAProcessor):
        super().__init__()
        self.model, self.processor = model, processor

    @property
    def config(self) -> VLAConfig:
        return self.model.config

    def inputs(self, observation: dict[str, Any]) -> VLAInputs:
        """The model's inputs, on the model's device (observations may arrive in host memory)."""
        return self.processor.inputs(observation).to(self.model.action_in_proj.weight.device)

    @torch.no_grad()
    def predict_action_chunk(self, observation: dict[str, Any], noise: torch.Tensor | None = None,
                             num_steps: int | None = None) -> torch.Tensor:
        """Env-unit actions ``[B, chunk, action_dim]`` for a LeRobot-style observation (ODE sampling)."""
        x = self.inputs(observation)
        noise = None if noise is None else noise.to(x.tokens.device)
        sampled = self.model.sample_actions(x.images, x.image_masks, x.tokens, x.token_mask, x.state,
                                            noise=noise, num_steps=num_steps)
        return self.processor.actions_out(sampled)

    def loss(self, observation: dict[str, Any], actions: torch.Tensor, noise: torch.Tensor | None = None,
             time: torch.Tensor | None = None, reduction: str = "mean",
             action_mask: torch.Tensor | None = None) -> torch.Tensor:
        """Flow-matching loss on demonstrations (env units ``[B, chunk, action_dim]``), averaged over the
        real action dims (padding excluded) and the chunk: a scalar, or ``[B]`` with ``reduction="none"``.

        ``action_mask`` ``[B, chunk]`` (bool): the rows that are real actions; a chunk that runs past
        its episode's end is padded, and its padding rows are left out of the average (LeRobot's
        ``action_is_pad``)."""
        x = self.inputs(observation)
        device = x.tokens.device  # demonstrations, noise and times may arrive in host memory
        noise, time = (None if t is None else t.to(device) for t in (noise, time))
        elements = self.model.loss_elements(x.images, x.image_masks, x.tokens, x.token_mask, x.state,
                                            self.processor.actions_in(actions).to(device), noise=noise, time=time)
        if action_mask is None:
            per_sample = elements[..., :self.config.action_dim].mean(dim=(1, 2))
        else:
            rows = elements[..., :self.config.action_dim].mean(dim=-1)
            weight = action_mask.to(device=rows.device, dtype=rows.dtype)
            per_sample = (rows * weight).sum(1) / weight.sum(1).clamp_min(1.0)
        return per_sample if reduction == "none" else per_sample.mean()


def _tokenizer_for(folder: Path, tokenizer):
    if tokenizer is None and (folder / "tokenizer").is_dir():
        return folder / "tokenizer"
    return tokenizer


def load_vla(folder: str | Path, *, family: str | None = None, architecture: VLAArchitecture | None = None,
             tokenizer=None, stats: dict[str, dict[str, torch.Tensor]] | None = None,
             device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> VLA:
    """Load a LeRobot π0/π0.5 checkpoint folder (module docstring) with no hub access.

    Args:
        folder: the checkpoint folder.
        family: ``"pi0"`` or ``"pi05"`` to insist on one (else read from ``config.json``).
        architecture: sizes, for checkpoints whose sizes are not their variant names' (tests' tiny ones).
        tokenizer: a tokenizer object or its local folder.
        stats: ``{"observation.state": {...}, "action": {...}}`` replacing the saved statistics.
        device / dtype: where and in what precision the network runs (statistics stay float32).
    """
    folder = Path(folder)
    config = read_vla_config(folder, family=family, architecture=architecture)
    features = {STATE: "STATE", ACTION: "ACTION"}
    input_norm = read_normalizer(folder, features, stats=stats)
    output_norm = read_normalizer(folder, {ACTION: "ACTION"}, pipeline="policy_postprocessor",
                                  registry_name="unnormalizer_processor", stats=stats)
    model = PiZero(config).to(dtype=dtype)
    load_weights(model, folder / "model.safetensors")
    processor = VLAProcessor(config, input_norm, output_norm, tokenizer=_tokenizer_for(folder, tokenizer))
    vla = VLA(model, processor).to(device)
    vla.eval()
    return vla


def load_processor_stats(vla: VLA, folder: str | Path) -> None:
    """Replace ``vla``'s state/action statistics with those saved in ``folder`` (a checkpoint's
    policy folder): a resumed run normalises with what it was trained with, not with statistics
    read again from its data or its initial model."""
    folder = Path(folder)
    saved_in = read_normalizer(folder, {STATE: "STATE", ACTION: "ACTION"})
    saved_out = read_normalizer(folder, {ACTION: "ACTION"}, pipeline="policy_postprocessor",
                                registry_name="unnormalizer_processor")
    vla.processor.input_norm.load_state_dict(saved_in.state_dict())
    vla.processor.output_norm.load_state_dict(saved_out.state_dict())
