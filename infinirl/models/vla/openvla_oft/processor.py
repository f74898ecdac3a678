"""OpenVLA-OFT's pre- and post-processing: images, prompt, proprio in; actions out.

* Images: per camera uint8 (or ``[0, 1]`` float) ``[B, H, W, 3]`` / ``[B, 3, H, W]`` at the
  checkpoint's resolution (224 for the published ones). OFT resizes beforehand (JPEG round trip and
  Lanczos in TensorFlow), which torch cannot reproduce bit for bit, so another size is an error
  unless ``resize=True`` (bicubic, antialiased: close, not identical). Each image is normalised
  with each backbone's mean/std (``preprocessor_config.json``; DINOv2 first) and the channels
  stacked: ``[B, N * 3 * backbones, S, S]``, the primary camera first.
* Prompt: ``"In: What action should the robot take to {instruction.lower()}?\\nOut:"``, tokenised
  with ``<s>``, then Llama-2's "▁" (29871) appended unless already last, as OFT does.
* Proprio (OFT's ``normalize_proprio``) and actions (``_unnormalize_actions``): the platform's
  bounds (``min``/``max``) or ``q01``/``q99`` of the chosen dataset (``unnorm_key``), dims whose
  ``mask`` is false passed through; proprio clipped to ``[-1, 1]``. :meth:`OFTProcessor.env_actions`
  adds OFT's eval-time gripper mapping for the env (LIBERO's -1 = open, +1 = close).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from infinirl.models.vla.openvla_oft.config import NORMALIZATIONS, OFTConfig

__all__ = ["OFTProcessor", "prompt_for", "select_stats"]

EPS = 1e-8  # OFT's guard on the span


def prompt_for(instruction: str) -> str:
    return f"In: What action should the robot take to {instruction.lower()}?\nOut:"


def select_stats(norm_stats: dict[str, Any], unnorm_key: str | None, source: str) -> tuple[str, dict[str, Any]]:
    """The statistics of one dataset; one-line errors for an ambiguous or unknown key."""
    if not norm_stats:
        raise ValueError(f"no normalisation statistics in {source}: keep dataset_statistics.json (written by OFT's "
                         "fine-tuning) in the checkpoint folder")
    if unnorm_key is None:
        if len(norm_stats) != 1:
            raise ValueError(f"{source} holds statistics of {len(norm_stats)} datasets: pass unnorm_key= one of "
                             f"{sorted(norm_stats)}")
        unnorm_key = next(iter(norm_stats))
    if unnorm_key not in norm_stats:
        raise ValueError(f"unnorm_key={unnorm_key!r} is not in {source}: choose one of {sorted(norm_stats)}")
    return unnorm_key, norm_stats[unnorm_key]


def _bounds(stats: dict[str, Any], feature: str, normalization: str, dim: int, source: str) -> torch.Tensor:
    """``[3, dim]``: low, high, mask (as float) of one feature."""
    low_name, high_name = NORMALIZATIONS[normalization]
    entry = stats.get(feature)
    if not isinstance(entry, dict) or low_name not in entry or high_name not in entry:
        raise ValueError(f"{source}: no {feature}.{low_name}/{feature}.{high_name} statistics ({normalization}) for "
                         f"the chosen dataset: fine-tuning writes them to dataset_statistics.json")
    low = torch.as_tensor(entry[low_name], dtype=torch.float64)
    high = torch.as_tensor(entry[high_name], dtype=torch.float64)
    mask = torch.as_tensor(entry.get("mask", [True] * low.numel()), dtype=torch.float64)
    if low.numel() != dim:
        raise ValueError(f"{source}: {feature} statistics have {low.numel()} dims, the platform {dim}: pass the "
                         "platform the checkpoint was fine-tuned for (platform=)")
    return torch.stack([low, high, mask])


class OFTProcessor(nn.Module):
    """Holds the chosen dataset's statistics (float64 buffers) and the tokenizer."""

    def __init__(self, config: OFTConfig, tokenizer, *, unnorm_key: str | None = None, proprio: bool = False,
                 resize: bool = False, source: str = "dataset_statistics.json"):
        super().__init__()
        self.config, self.tokenizer, self.resize = config, tokenizer, resize
        self.unnorm_key, stats = select_stats(config.norm_stats, unnorm_key, source)
        platform = config.platform
        self.register_buffer("action_bounds", _bounds(stats, "action", platform.normalization,
                                                      platform.action_dim, source))
        bounds = _bounds(stats, "proprio", platform.normalization, platform.proprio_dim, source) if proprio else None
        self.register_buffer("proprio_bounds", bounds)
        self.register_buffer("means", torch.tensor(config.image_means, dtype=torch.float32))
        self.register_buffer("stds", torch.tensor(config.image_stds, dtype=torch.float32))

    # --- images ------------------------------------------------------------------------------

    def image(self, name: str, image: Any) -> torch.Tensor:
        """One camera ``[B, H, W, 3]`` -> ``[B, 3 * backbones, S, S]`` normalised."""
        image = torch.as_tensor(image)
        if image.dim() != 4 or 3 not in (image.shape[1], image.shape[-1]):
            raise ValueError(f"camera {name!r}: image of shape {list(image.shape)}; expected [B, H, W, 3] or "
                             "[B, 3, H, W] (uint8, or float in [0, 1])")
        if image.shape[1] != 3:
            image = image.permute(0, 3, 1, 2)
        image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
        size = self.config.image_size
        if tuple(image.shape[2:]) != (size, size):
            if not self.resize:
                raise ValueError(f"camera {name!r}: image of {image.shape[2]}x{image.shape[3]}, the checkpoint takes "
                                 f"{size}x{size}: resize as OFT does before (resize_image_for_policy) or pass "
                                 "resize=True (bicubic)")
            image = F.interpolate(image, size=(size, size), mode="bicubic", align_corners=False,
                                  antialias=True).clamp(0, 1)
        means, stds = self.means.to(image.device), self.stds.to(image.device)
        return torch.cat([(image - means[i, :, None, None]) / stds[i, :, None, None] for i in range(len(means))],
                         dim=1)

    def pixel_values(self, images: Sequence[Any]) -> torch.Tensor:
        """Camera batches, the primary first -> ``[B, N * 3 * backbones, S, S]``."""
        if len(images) != self.config.num_images:
            raise ValueError(f"{len(images)} camera image(s) given, the model was set up for num_images="
                             f"{self.config.num_images}")
        return torch.cat([self.image(f"#{i}", image) for i, image in enumerate(images)], dim=1)

    # --- prompt ------------------------------------------------------------------------------

    def tokenize(self, instructions: Sequence[str], device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Right-padded ``[B, L]`` ids (``<s>`` first, "▁" last) and their lengths ``[B]``."""
        if isinstance(instructions, str):
            raise ValueError("give one instruction per sample (a list of str), got a single str")
        if self.tokenizer is None:
            raise ValueError("no tokenizer: the checkpoint folder holds OpenVLA's (Llama-2) tokenizer files; pass "
                             "tokenizer= (a folder or object) if they were removed")
        limit = (self.config.max_positions - self.config.num_patches - self.config.num_action_tokens - 2
                 - int(self.proprio_bounds is not None))
        rows = []
        for instruction in instructions:
            ids = list(self.tokenizer(prompt_for(instruction), add_special_tokens=True)["input_ids"])
            if ids[-1] != self.config.empty_token_id:
                ids.append(self.config.empty_token_id)
            if len(ids) > limit:
                raise ValueError(f"instruction {instruction[:40]!r}... makes a {len(ids)}-token prompt; with the image "
                                 f"patches and {self.config.num_action_tokens} action tokens at most {limit} fit the "
                                 f"Llama's {self.config.max_positions} positions: shorten it")
            rows.append(ids)
        lengths = torch.tensor([len(ids) for ids in rows])
        tokens = torch.zeros(len(rows), int(lengths.max()), dtype=torch.long)
        for i, ids in enumerate(rows):
            tokens[i, :len(ids)] = torch.as_tensor(ids)
        return tokens.to(device), lengths.to(device)

    # --- proprio and actions -----------------------------------------------------------------

    def proprio(self, raw: Any) -> torch.Tensor:
        """OFT's ``normalize_proprio``: ``[B, proprio_dim]`` -> ``[-1, 1]`` (float64)."""
        if self.proprio_bounds is None:
            raise ValueError("this processor was built without proprio statistics (the checkpoint has no proprio "
                             "projector)")
        raw = torch.as_tensor(raw, dtype=torch.float64)
        dim = self.config.platform.proprio_dim
        if raw.dim() != 2 or raw.shape[1] != dim:
            raise ValueError(f"proprio of shape {list(raw.shape)}, the checkpoint expects [B, {dim}]")
        low, high, mask = self.proprio_bounds.to(raw.device)
        normalized = 2 * (raw - low) / (high - low + EPS) - 1
        return torch.where(mask.bool(), normalized, raw).clamp(-1.0, 1.0)

    def actions_out(self, normalized: torch.Tensor) -> torch.Tensor:
        """OFT's ``_unnormalize_actions``: ``[..., action_dim]`` in ``[-1, 1]`` -> env units (float64)."""
        low, high, mask = self.action_bounds.to(normalized.device)
        x = normalized.to(torch.float64)
        return torch.where(mask.bool(), 0.5 * (x + 1) * (high - low + EPS) + low, x)

    def env_actions(self, normalized: torch.Tensor) -> torch.Tensor:
        """What the env executes: :meth:`actions_out`, then, on a platform whose gripper OpenVLA's data
        loader flipped (``Platform.invert_gripper``, LIBERO), the last dim ``g`` (0 = close, 1 = open)
        binarised into the env's -1 = open / +1 = close as OFT's eval does: ``-sign(2g - 1)``."""
        actions = self.actions_out(normalized)
        if not self.config.platform.invert_gripper:
            return actions
        gripper = -torch.sign(2 * actions[..., -1:] - 1)
        return torch.cat([actions[..., :-1], gripper], dim=-1)

    def actions_in(self, actions: torch.Tensor) -> torch.Tensor:
        """Env units -> ``[-1, 1]`` (the inverse of :meth:`actions_out`, for demonstrations)."""
        low, high, mask = self.action_bounds.to(actions.device)
        x = torch.as_tensor(actions, dtype=torch.float64)
        return torch.where(mask.bool(), 2 * (x - low) / (high - low + EPS) - 1, x)


def load_tokenizer(folder: Path, tokenizer: Any):
    """The folder's tokenizer (``AutoTokenizer``, local files only), or the one given."""
    if tokenizer is not None and not isinstance(tokenizer, (str, Path)):
        return tokenizer
    from transformers import AutoTokenizer

    path = Path(tokenizer) if tokenizer is not None else folder
    if not (path / "tokenizer_config.json").is_file():
        raise FileNotFoundError(f"no tokenizer_config.json in {path}: OpenVLA folders keep the Llama-2 tokenizer "
                                "files; pass tokenizer= their folder")
    return AutoTokenizer.from_pretrained(str(path), local_files_only=True, trust_remote_code=False)
