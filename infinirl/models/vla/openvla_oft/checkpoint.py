"""Map a published OpenVLA(-OFT) folder's weights onto :class:`~.model.OpenVLAOFT`.

``model.safetensors`` or sharded ``model-*-of-*.safetensors`` + ``model.safetensors.index.json``
(``save_pretrained``'s layout), keys as ``OpenVLAForActionPrediction`` names them:

========================================================  ==========================================
published                                                 ours
========================================================  ==========================================
``vision_backbone.featurizer.`` / ``fused_featurizer.``   ``vision.featurizers.0.`` / ``.1.``
  ``patch_embed.proj.`` ``pos_embed`` ``cls_token``       ``patch_embed.`` ``pos_embed`` ``cls_token``
  ``reg_token``                                           ``reg_token``
  ``blocks.<i>.norm1/norm2.``                             ``blocks.<i>.norm1/norm2.`` (SigLIP: ``layer_norm1/2.``)
  ``blocks.<i>.attn.qkv.``                                split into the q/k/v projections
  ``blocks.<i>.attn.proj.``                               ``attention.o_proj.`` (SigLIP: ``self_attn.out_proj.``)
  ``blocks.<i>.mlp.fc1/fc2.``                             the same
  ``blocks.<i>.ls1/ls2.scale_factor``                     ``layer_scale1/2.lambda1`` (DINOv2)
``projector.fc1/fc2/fc3.``                                ``projector.`` the same
``language_model.model.`` / ``language_model.lm_head.``   ``llm.model.`` / ``llm.lm_head.``
========================================================  ==========================================

Unused by design, skipped: each ViT's last block, final ``norm``, SigLIP's ``attn_pool`` head (see
:mod:`.vision`). Every other key must map, every parameter must be filled, shapes must agree:
otherwise one line naming the first offending key. The heads' ``.pt`` files hold a (possibly
DDP-wrapped, ``module.``-prefixed) ``state_dict`` of OFT's ``L1RegressionActionHead``
(``model.layer_norm1``, ``model.fc1``, ``model.mlp_resnet_blocks.<i>.ffn.0/1``, ``model.layer_norm2``,
``model.fc2``) or ``ProprioProjector`` (``fc1``, ``fc2``).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import torch
from safetensors import safe_open

from infinirl.models.vla.openvla_oft.model import OpenVLAOFT

__all__ = ["block_layouts", "find_component", "load_component", "load_weights", "map_checkpoint_keys", "read_weights",
           "vit_targets"]

FEATURIZERS = ("vision_backbone.featurizer.", "vision_backbone.fused_featurizer.")
BLOCK = re.compile(r"blocks\.(\d+)\.(.+)")
UNUSED_VIT = ("norm.", "attn_pool.", "fc_norm.", "head.")
VIT_TOP = {"patch_embed.proj.": "patch_embed.", "pos_embed": "pos_embed", "cls_token": "cls_token",
           "reg_token": "reg_token"}
BLOCK_NAMES = {
    "dinov2": {"norm1.": "norm1.", "norm2.": "norm2.", "attn.proj.": "attention.o_proj.", "mlp.fc1.": "mlp.fc1.",
               "mlp.fc2.": "mlp.fc2.", "ls1.scale_factor": "layer_scale1.lambda1",
               "ls2.scale_factor": "layer_scale2.lambda1"},
    "siglip": {"norm1.": "layer_norm1.", "norm2.": "layer_norm2.", "attn.proj.": "self_attn.out_proj.",
               "mlp.fc1.": "mlp.fc1.", "mlp.fc2.": "mlp.fc2."},
}
QKV = {"dinov2": ("attention.q_proj.", "attention.k_proj.", "attention.v_proj."),
       "siglip": ("self_attn.q_proj.", "self_attn.k_proj.", "self_attn.v_proj.")}
# transformers before its attention refactor builds Dinov2WithRegistersLayer with a nested attention
# (query/key/value, output.dense); the layout is read off the model actually built, so a folder
# loads under either release.
BLOCK_NAMES["dinov2_nested"] = {**BLOCK_NAMES["dinov2"], "attn.proj.": "attention.output.dense."}
QKV["dinov2_nested"] = ("attention.attention.query.", "attention.attention.key.", "attention.attention.value.")
HEAD_NAMES = (("model.mlp_resnet_blocks.", "blocks."), ("model.", ""))
HEAD_BLOCK_PARTS = ((".ffn.0.", ".norm."), (".ffn.1.", ".linear."))


def read_weights(folder: Path) -> dict[str, torch.Tensor]:
    """All tensors of ``model.safetensors`` or of the shards an index names."""
    index = folder / "model.safetensors.index.json"
    single = folder / "model.safetensors"
    if index.is_file():
        files = sorted(set(json.loads(index.read_text())["weight_map"].values()))
    elif single.is_file():
        files = [single.name]
    else:
        raise FileNotFoundError(f"no model.safetensors (or model.safetensors.index.json) in {folder}: an OpenVLA-OFT "
                                "folder holds the weights save_pretrained wrote")
    tensors: dict[str, torch.Tensor] = {}
    for name in files:
        path = folder / name
        if not path.is_file():
            raise FileNotFoundError(f"{index} names {name}, which is not in {folder}: copy every shard")
        with safe_open(str(path), framework="pt") as handle:
            tensors.update({key: handle.get_tensor(key) for key in handle.keys()})
    return tensors


def vit_targets(rest: str, prefix: str, kind: str, depth: int) -> list[tuple[str, int | None]] | None:
    """Our names for one ViT key (``[]`` when unused by design, ``None`` when unknown); the int is the
    q/k/v chunk of a fused ``qkv`` tensor."""
    for published, ours in VIT_TOP.items():
        if rest == published or (published.endswith(".") and rest.startswith(published)):
            return [(prefix + ours + rest[len(published):], None)]
    if rest.startswith(UNUSED_VIT):
        return []
    match = BLOCK.fullmatch(rest)
    if match is None:
        return None
    block, tail = int(match.group(1)), match.group(2)
    if block == depth - 1:
        return []
    base = f"{prefix}blocks.{block}."
    if tail.startswith("attn.qkv."):
        leaf = tail[len("attn.qkv."):]
        return [(base + name + leaf, i) for i, name in enumerate(QKV[kind])]
    for published, ours in BLOCK_NAMES[kind].items():
        if tail.startswith(published):
            return [(base + ours + tail[len(published):], None)]
    return None


def block_layouts(model: OpenVLAOFT, names: set[str]) -> list[str]:
    """The name layout of each ViT's blocks in the model as built (``names``: its state-dict keys):
    the ViT's kind, or ``dinov2_nested``."""
    layouts = []
    for i, spec in enumerate(model.config.vision):
        nested = f"vision.featurizers.{i}.blocks.0.attention.attention.query.weight" in names
        layouts.append("dinov2_nested" if spec.kind == "dinov2" and nested else spec.kind)
    return layouts


def _targets(key: str, model: OpenVLAOFT, layouts: list[str]) -> list[tuple[str, int | None]] | None:
    for i, published in enumerate(FEATURIZERS):
        if key.startswith(published) and i < len(model.config.vision):
            spec = model.config.vision[i]
            return vit_targets(key[len(published):], f"vision.featurizers.{i}.", layouts[i], spec.depth)
    if key.startswith("projector."):
        return [(key, None)]
    if key.startswith("language_model."):
        return [("llm." + key[len("language_model."):], None)]
    return None


def _more(items: list) -> str:
    return f" (and {len(items) - 1} more)" if len(items) > 1 else ""


def _check(mapped: dict[str, torch.Tensor], expected: dict[str, torch.Tensor], source: str, what: str) -> None:
    missing = sorted(set(expected) - set(mapped))
    if missing:
        raise ValueError(f"{source}: no weights for {missing[0]!r}{_more(missing)} of the {what}: is this a "
                         "checkpoint of another family or of other sizes?")
    for name, tensor in mapped.items():
        if tuple(tensor.shape) != tuple(expected[name].shape):
            raise ValueError(f"{source}: {name!r} has shape {list(tensor.shape)}, the model built from config.json "
                             f"expects {list(expected[name].shape)}: pass vision=/platform= for a checkpoint "
                             "of other sizes")


def map_checkpoint_keys(tensors: dict[str, torch.Tensor], model: OpenVLAOFT, source: str) -> dict[str, torch.Tensor]:
    """Our state dict (VLA part) from the published one; one-line errors for unknown/missing/misshapen keys."""
    expected = {k: v for k, v in model.state_dict().items()
                if not k.startswith(("action_head.", "proprio_projector."))}
    layouts = block_layouts(model, set(expected))
    mapped: dict[str, torch.Tensor] = {}
    unknown: list[str] = []
    for key, tensor in tensors.items():
        targets = _targets(key, model, layouts)
        if targets is None:
            unknown.append(key)
            continue
        for name, chunk in targets:
            value = tensor.chunk(3, dim=0)[chunk] if chunk is not None else tensor
            if name not in expected:
                unknown.append(key)
                break
            mapped[name] = value
    if unknown:
        raise ValueError(f"{source}: key {unknown[0]!r}{_more(unknown)} has no place in an OpenVLA-OFT model: is this "
                         "a checkpoint of another family?")
    _check(mapped, expected, source, "OpenVLA-OFT model")
    return mapped


def find_component(folder: Path, name: str) -> Path | None:
    """OFT's ``<name>--<step>_checkpoint.pt`` in ``folder`` (one expected), or None."""
    found = sorted(folder.glob(f"{name}--*checkpoint.pt"))
    if len(found) > 1:
        raise ValueError(f"{folder} holds {len(found)} {name} checkpoints ({', '.join(p.name for p in found)}): keep "
                         "the one matching the VLA weights")
    return found[0] if found else None


def _head_key(key: str) -> str:
    for published, ours in HEAD_NAMES:
        if key.startswith(published):
            key = ours + key[len(published):]
            break
    for published, ours in HEAD_BLOCK_PARTS:
        key = key.replace(published, ours)
    return key


def load_component(module: torch.nn.Module, path: Path, *, action_head: bool) -> None:
    """Fill an OFT head from its ``.pt`` (``module.`` prefixes of DDP removed)."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    state = {key[len("module."):] if key.startswith("module.") else key: value for key, value in state.items()}
    if action_head:
        state = {_head_key(key): value for key, value in state.items()}
    expected = module.state_dict()
    unknown = sorted(set(state) - set(expected))
    if unknown:
        raise ValueError(f"{path}: key {unknown[0]!r}{_more(unknown)} has no place in the "
                         f"{type(module).__name__}: is this the right file?")
    _check(state, expected, str(path), type(module).__name__)
    module.load_state_dict({k: v.to(expected[k].dtype) for k, v in state.items()}, strict=True)


def load_weights(model: OpenVLAOFT, folder: Path) -> None:
    """Fill the VLA part of ``model`` from the folder's safetensors (cast to the model's dtype)."""
    mapped = map_checkpoint_keys(read_weights(folder), model, source=str(folder))
    state = model.state_dict()
    missing, unexpected = model.load_state_dict({k: v.to(state[k].dtype) for k, v in mapped.items()}, strict=False)
    assert not unexpected, unexpected
    heads = [name for name in missing if not name.startswith(("action_head.", "proprio_projector."))]
    assert not heads, heads
