"""FSDP2 sharding with summed gradients, shared by every FSDP2 trainer (LLM engine, embodied actor).

Gradients are summed over ranks, never averaged: every loss in InfiniRL is normalised by a
*global* denominator (the whole mini-batch over all ranks), so the gradient of the mini-batch loss
is the sum of the per-rank gradients. FSDP2 averages by default; :func:`shard` sets
``gradient_divide_factor=1`` and forces plain ``SUM`` collectives on *every* FSDP module (neither
setter recurses into sub-modules, and setting only the root would leave the layers averaging).
``SUM`` rather than NCCL's ``PREMUL_SUM(1.0)`` because gloo has no ``PREMUL_SUM``; the result is
the same.

Sharded modules return no view tensors (:func:`outputs_without_views`). FSDP2 registers its
pre-backward hook (the all-gather of the parameters the backward needs) on the tensors a sharded
module returns; an in-place op on a returned *view* would re-base its autograd history and drop
that hook, so FSDP2 warns whenever a module returns a view. A linear layer with a bias returns
one for 3-D inputs (``addmm`` on the flattened rows, viewed back), which is what a critic's value
head and the embodied policies' heads are.
"""

from __future__ import annotations

from collections.abc import MutableMapping
from typing import Any

import torch
from torch import nn
from torch.distributed.fsdp import FSDPModule, MixedPrecisionPolicy, fully_shard
from torch.distributed.tensor import DTensor

__all__ = ["decoder_layers", "full_tensor", "outputs_without_views", "shard", "sum_gradients_over_ranks"]


def decoder_layers(model: nn.Module) -> list[nn.Module]:
    """Modules to shard as separate FSDP groups: HF's ``_no_split_modules`` (the decoder layers).

    One group per layer lets FSDP all-gather one layer at a time (peak memory about one layer's
    parameters) and overlap communication with the previous layer's compute.
    """
    class_names: set[str] = set()
    for module in model.modules():
        class_names.update(getattr(module, "_no_split_modules", None) or [])
    return [m for m in model.modules() if type(m).__name__ in class_names]


def shard(model: nn.Module, mesh=None, mp_policy: MixedPrecisionPolicy | None = None) -> nn.Module:
    """``fully_shard`` every decoder layer (:func:`decoder_layers`), then the root, with gradients
    summed over ranks; ``mesh``/``mp_policy`` left out take ``fully_shard``'s defaults."""
    options: dict[str, Any] = {}
    if mesh is not None:
        options["mesh"] = mesh
    if mp_policy is not None:
        options["mp_policy"] = mp_policy
    for module in [*decoder_layers(model), model]:
        module.register_forward_hook(outputs_without_views)  # before fully_shard: runs before its hook
        fully_shard(module, **options)
    sum_gradients_over_ranks(model)
    return model


def sum_gradients_over_ranks(model: nn.Module) -> None:
    """Make every FSDP module under ``model`` reduce-scatter with ``SUM`` and divide by nothing."""
    for module in model.modules():
        if isinstance(module, FSDPModule):
            module.set_gradient_divide_factor(1.0)
            module.set_force_sum_reduction_for_comms(True)


def outputs_without_views(module: nn.Module, args: Any, output: Any) -> Any:
    """Forward hook: the output with every view tensor that needs a gradient replaced by a copy.

    Registered before ``fully_shard``, it runs before FSDP2's own post-forward hook, which then
    registers its pre-backward hook on tensors no later in-place op can re-base. Copies are made
    only with grad enabled (no-grad forwards return what the model returns) and only of views.
    """
    if not torch.is_grad_enabled():
        return None
    return _without_views(output)


def _without_views(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.clone() if value.requires_grad and value._base is not None else value
    if isinstance(value, MutableMapping):  # dicts and transformers' ModelOutput (which keeps attributes in step)
        for key in list(value.keys()):
            value[key] = _without_views(value[key])
        return value
    if isinstance(value, tuple):
        items = [_without_views(item) for item in value]
        return type(value)(*items) if hasattr(value, "_fields") else tuple(items)
    if isinstance(value, list):
        return [_without_views(item) for item in value]
    return value


def full_tensor(tensor: torch.Tensor) -> torch.Tensor:
    """Unshard a DTensor (a collective: every rank must call it in the same order)."""
    return tensor.full_tensor() if isinstance(tensor, DTensor) else tensor
