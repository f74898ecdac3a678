"""Raw observations -> the model's inputs, and its outputs -> actions (LeRobot's π0/π0.5 processors).

* Images: each camera of ``config.camera_keys`` as uint8 or ``[0, 1]`` float, ``[B, H, W, 3]`` or
  ``[B, 3, H, W]``; resized with padding to the checkpoint's square ``image_resolution`` (bilinear,
  aspect kept, black bars) and mapped to ``[-1, 1]``. Cameras absent from the observation become
  all ``-1`` images with a false mask, placed after the present ones (LeRobot's order, which
  decides the token positions). LeRobot pads with -1 *before* its ``[0, 1] -> [-1, 1]`` map
  (bars at -3); openpi pads black, and so do we: the two agree whenever no padding is needed.
* State: normalised (``observation.state``), zero-padded to ``max_state_dim``.
* Instruction: an env's wording is first replaced by the one the model was trained with
  (``config.instructions``, when it lists it). π0 appends ``"\\n"``; π0.5 (``discrete_state``) writes
  ``"Task: <task>, State: <256-bin ints>;\\nAction: "``. Tokenised, right-padded to
  ``tokenizer_max_length``; a longer prompt is an error, not a silent truncation.
* Actions: the model's normalised, padded chunk -> the first ``action_dim`` dims, unnormalised.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from infinirl.models.vla.config import VLAConfig
from infinirl.models.vla.normalize import Normalizer

__all__ = ["ACTION", "STATE", "TASK", "VLAInputs", "VLAProcessor", "load_tokenizer", "resize_with_pad"]

STATE, ACTION, TASK = "observation.state", "action", "task"


@dataclass
class VLAInputs:
    """What :class:`~.model.PiZero` takes for a batch of observations."""

    images: list[torch.Tensor]
    image_masks: list[torch.Tensor]
    tokens: torch.Tensor
    token_mask: torch.Tensor
    state: torch.Tensor | None

    def to(self, device) -> VLAInputs:
        def move(x):
            return None if x is None else x.to(device)

        return VLAInputs(images=[move(i) for i in self.images], image_masks=[move(m) for m in self.image_masks],
                         tokens=move(self.tokens), token_mask=move(self.token_mask), state=move(self.state))


def resize_with_pad(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``[B, C, H, W]`` floats in ``[0, 1]`` -> ``[B, C, height, width]``: bilinear resize keeping the
    aspect ratio (openpi's ``resize_with_pad``), centred, padded with 0 (black)."""
    _, _, cur_h, cur_w = images.shape
    ratio = max(cur_w / width, cur_h / height)
    new_h, new_w = int(cur_h / ratio), int(cur_w / ratio)
    resized = F.interpolate(images, size=(new_h, new_w), mode="bilinear", align_corners=False)
    top, extra_h = divmod(height - new_h, 2)
    left, extra_w = divmod(width - new_w, 2)
    return F.pad(resized, (left, left + extra_w, top, top + extra_h), value=0.0)


def load_tokenizer(tokenizer: Any):
    """A tokenizer object as given, or loaded from a local folder (``AutoTokenizer``, no hub)."""
    if tokenizer is None or not isinstance(tokenizer, (str, Path)):
        return tokenizer
    from transformers import AutoTokenizer

    if not Path(tokenizer).is_dir():
        raise FileNotFoundError(f"tokenizer={tokenizer}: not a folder; pass the local folder of the checkpoint's "
                                "tokenizer (PaliGemma's: google/paligemma-3b-pt-224)")
    return AutoTokenizer.from_pretrained(str(tokenizer), local_files_only=True)


class VLAProcessor(nn.Module):
    """Pre- and post-processing of one checkpoint (module docstring); holds the statistics as buffers."""

    def __init__(self, config: VLAConfig, input_norm: Normalizer, output_norm: Normalizer, tokenizer=None):
        super().__init__()
        self.config = config
        self.input_norm, self.output_norm = input_norm, output_norm
        self.tokenizer = load_tokenizer(tokenizer)

    # --- images ------------------------------------------------------------------------------

    def image(self, key: str, image: torch.Tensor) -> torch.Tensor:
        """One camera's batch -> ``[B, 3, R, R]`` float32 in ``[-1, 1]``."""
        image = torch.as_tensor(image)
        if image.dim() != 4 or 3 not in (image.shape[1], image.shape[-1]):
            raise ValueError(f"camera {key!r}: image of shape {list(image.shape)}; expected [B, H, W, 3] or "
                             f"[B, 3, H, W] (uint8, or float in [0, 1])")
        if image.shape[1] != 3:
            image = image.permute(0, 3, 1, 2)
        image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
        resolution = self.config.image_resolution
        if tuple(image.shape[2:]) != tuple(resolution):
            image = resize_with_pad(image, *resolution)
        return image * 2.0 - 1.0

    def images(self, observation: dict[str, Any]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        present = [key for key in self.config.camera_keys if key in observation]
        if not present:
            raise ValueError(f"no camera image in the observation: expected some of {list(self.config.camera_keys)}, "
                             f"got keys {sorted(observation)}")
        images = [self.image(key, observation[key]) for key in present]
        batch, device = images[0].shape[0], images[0].device
        masks = [torch.ones(batch, dtype=torch.bool, device=device) for _ in present]
        for _key in self.config.camera_keys[len(present):]:
            images.append(-torch.ones_like(images[0]))
            masks.append(torch.zeros(batch, dtype=torch.bool, device=device))
        return images, masks

    # --- state, prompt, tokens ---------------------------------------------------------------

    def state(self, raw: torch.Tensor) -> torch.Tensor:
        """Normalised state, zero-padded to ``max_state_dim`` ``[B, max_state_dim]``."""
        raw = torch.as_tensor(raw).float()
        if raw.dim() != 2 or raw.shape[1] != self.config.state_dim:
            raise ValueError(f"{STATE}: shape {list(raw.shape)}, the checkpoint expects [B, {self.config.state_dim}]")
        normalized = self.input_norm.normalize(STATE, raw)
        return F.pad(normalized, (0, self.config.max_state_dim - normalized.shape[1]))

    def prompts(self, tasks: Sequence[str], state: torch.Tensor) -> list[str]:
        if isinstance(tasks, str):
            raise ValueError(f"{TASK}: give one instruction per sample (a list of str), got a single str")
        tasks = [self.config.instructions.get(task, task) for task in tasks]
        if not self.config.switches.discrete_state:
            return [task if task.endswith("\n") else f"{task}\n" for task in tasks]
        bins = np.linspace(-1, 1, 256 + 1)[:-1]
        discrete = np.digitize(state.detach().cpu().numpy(), bins=bins) - 1
        prompts = []
        for task, row in zip(tasks, discrete, strict=True):
            cleaned = task.strip().replace("_", " ").replace("\n", " ")
            prompts.append(f"Task: {cleaned}, State: {' '.join(map(str, row))};\nAction: ")
        return prompts

    def tokenize(self, prompts: Sequence[str], device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``[B, tokenizer_max_length]`` ids (right-padded) and their mask."""
        if self.tokenizer is None:
            raise ValueError("no tokenizer: pass tokenizer= (the local folder of PaliGemma's tokenizer, "
                             "google/paligemma-3b-pt-224, or a tokenizer object) to load_vla")
        limit = self.config.tokenizer_max_length
        ids = self.tokenizer(list(prompts), add_special_tokens=True)["input_ids"]
        for prompt, row in zip(prompts, ids, strict=True):
            if len(row) > limit:
                raise ValueError(f"instruction {prompt[:40]!r}... is {len(row)} tokens, more than the checkpoint's "
                                 f"tokenizer_max_length {limit}: shorten it")
        pad = self.tokenizer.pad_token_id or 0
        tokens = torch.full((len(ids), limit), pad, dtype=torch.long)
        mask = torch.zeros((len(ids), limit), dtype=torch.bool)
        for i, row in enumerate(ids):
            tokens[i, :len(row)] = torch.as_tensor(row, dtype=torch.long)
            mask[i, :len(row)] = True
        return tokens.to(device), mask.to(device)

    # --- the whole observation, and the actions ----------------------------------------------

    def inputs(self, observation: dict[str, Any]) -> VLAInputs:
        """LeRobot-style observation (camera keys, ``observation.state``, ``task``) -> model inputs."""
        images, masks = self.images(observation)
        if STATE not in observation:
            raise ValueError(f"the observation has no {STATE!r} (keys: {sorted(observation)})")
        if TASK not in observation:
            raise ValueError(f"the observation has no {TASK!r} instruction list (keys: {sorted(observation)})")
        state = self.state(observation[STATE]).to(images[0].device)
        tokens, token_mask = self.tokenize(self.prompts(observation[TASK], state), device=images[0].device)
        return VLAInputs(images=images, image_masks=masks, tokens=tokens, token_mask=token_mask,
                         state=None if self.config.switches.discrete_state else state)

    def actions_in(self, actions: torch.Tensor) -> torch.Tensor:
        """Env-unit actions ``[B, K, action_dim]`` -> normalised, padded ``[B, K, max_action_dim]``."""
        normalized = self.input_norm.normalize(ACTION, torch.as_tensor(actions).float())
        return F.pad(normalized, (0, self.config.max_action_dim - normalized.shape[-1]))

    def actions_out(self, actions: torch.Tensor) -> torch.Tensor:
        """The model's ``[B, K, max_action_dim]`` -> env-unit ``[B, K, action_dim]``."""
        return self.output_norm.unnormalize(ACTION, actions[..., :self.config.action_dim])
