"""Map a published π0/π0.5 ``model.safetensors`` onto :class:`~.model.PiZero`.

Key layouts read (LeRobot prefixes every key with ``model.``; openpi's PyTorch conversion does not):

=====================================================================  =========================
published (after the optional ``model.``)                              ours
=====================================================================  =========================
``paligemma_with_expert.paligemma.model.vision_tower.vision_model.``   ``vision_tower.``
``paligemma_with_expert.paligemma.model.multi_modal_projector.``       ``projector.``
``paligemma_with_expert.paligemma.model.language_model.``              ``vlm.``
``paligemma_with_expert.gemma_expert.model.``                          ``expert.``
``action_in_proj.`` ``action_out_proj.`` ``state_proj.`` ``*time_mlp_*``  the same
=====================================================================  =========================

(and transformers' pre-4.52 PaliGemma layout, ``paligemma.language_model.model.`` /
``paligemma.vision_tower.`` / ``paligemma.multi_modal_projector.``). The two ``lm_head`` weights are
not used by an action model and are skipped, except that PaliGemma ties its ``lm_head`` to the
token embedding and safetensors stores a tied pair once (LeRobot's files keep only ``lm_head``), so
the embedding is read from ``lm_head`` when its own key is absent. Older π0 files name the time
MLP ``time_mlp_*`` and older π0.5 files ``action_time_mlp_*`` (LeRobot renames both); so do we.

Every other key must map to a parameter and every parameter must be filled: a checkpoint of
another family or of other sizes fails with one line naming the first offending key.
"""

from __future__ import annotations

from pathlib import Path

import torch
from safetensors import safe_open

from infinirl.models.vla.model import PiZero

__all__ = ["load_weights", "map_checkpoint_keys", "read_safetensors"]

PREFIXES = (
    ("paligemma_with_expert.paligemma.model.vision_tower.vision_model.", "vision_tower.{vision}"),
    ("paligemma_with_expert.paligemma.vision_tower.vision_model.", "vision_tower.{vision}"),
    ("paligemma_with_expert.paligemma.model.multi_modal_projector.", "projector."),
    ("paligemma_with_expert.paligemma.multi_modal_projector.", "projector."),
    ("paligemma_with_expert.paligemma.model.language_model.", "vlm."),
    ("paligemma_with_expert.paligemma.language_model.model.", "vlm."),
    ("paligemma_with_expert.gemma_expert.model.", "expert."),
)
TIED_EMBEDDING = ("paligemma_with_expert.paligemma.lm_head.weight",
                  "paligemma_with_expert.paligemma.language_model.lm_head.weight")
UNUSED = (*TIED_EMBEDDING, "paligemma_with_expert.gemma_expert.lm_head.weight")
TIME_MLP_ALIASES = (("time_mlp_in.", "action_time_mlp_in."), ("time_mlp_out.", "action_time_mlp_out."))


def read_safetensors(path: str | Path) -> dict[str, torch.Tensor]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {path.name} in {path.parent}: a π0/π0.5 checkpoint folder holds LeRobot's "
                                "model.safetensors next to its config.json")
    with safe_open(str(path), framework="pt") as handle:
        return {key: handle.get_tensor(key) for key in handle.keys()}


def _alias(name: str, ours: set[str]) -> str:
    """Apply the time-MLP renames in whichever direction the model needs."""
    for old, new in TIME_MLP_ALIASES:
        for source, target in ((old, new), (new, old)):
            if name.startswith(source) and name not in ours and target + name[len(source):] in ours:
                return target + name[len(source):]
    return name


def map_checkpoint_keys(tensors: dict[str, torch.Tensor], model: PiZero, source: str = "model.safetensors"
                        ) -> dict[str, torch.Tensor]:
    """Our state dict from a published one; one-line errors for unknown, missing or misshapen keys."""
    expected = model.state_dict()
    ours = set(expected)
    vision = "vision_model." if any(key.startswith("vision_tower.vision_model.") for key in ours) else ""
    strip = "model." if tensors and all(key.startswith("model.") for key in tensors) else ""
    mapped: dict[str, torch.Tensor] = {}
    unexpected: list[str] = []
    tied = None
    for key, tensor in tensors.items():
        name = key[len(strip):]
        if name in UNUSED:
            if name in TIED_EMBEDDING:
                tied = tensor
            continue
        for published, target in PREFIXES:
            if name.startswith(published):
                name = target.format(vision=vision) + name[len(published):]
                break
        name = _alias(name, ours)
        if name in ours:
            mapped[name] = tensor
        else:
            unexpected.append(key)
    if "vlm.embed_tokens.weight" not in mapped and tied is not None:
        mapped["vlm.embed_tokens.weight"] = tied
    family = model.config.family
    if unexpected:
        raise ValueError(f"{source}: key {unexpected[0]!r} has no place in a '{family}' model"
                         f"{f' (and {len(unexpected) - 1} more)' if len(unexpected) > 1 else ''}: is this a "
                         f"checkpoint of another family?")
    missing = sorted(ours - set(mapped))
    if missing:
        raise ValueError(f"{source}: no weights for {missing[0]!r}"
                         f"{f' (and {len(missing) - 1} more)' if len(missing) > 1 else ''} of the '{family}' "
                         f"model: is this a checkpoint of another family?")
    for name, tensor in mapped.items():
        if tuple(tensor.shape) != tuple(expected[name].shape):
            raise ValueError(f"{source}: {name!r} has shape {list(tensor.shape)}, the model built from config.json "
                             f"expects {list(expected[name].shape)}: pass architecture=VLAArchitecture(...) for a "
                             f"checkpoint whose sizes are not its variants'")
    return mapped


def load_weights(model: PiZero, path: str | Path) -> None:
    """Fill ``model`` from a published ``model.safetensors`` (cast to the model's dtype)."""
    mapped = map_checkpoint_keys(read_safetensors(path), model, source=str(path))
    dtype = model.dtype
    state = {name: tensor.to(dtype) if tensor.is_floating_point() else tensor for name, tensor in mapped.items()}
    model.load_state_dict(state, strict=True)
