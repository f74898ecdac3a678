"""LoRA adapters (peft): put them on a model, and fold them back into plain HF weights for export.

The rollout engine loads a plain model under the original parameter names, so a LoRA trainer's
exported weights are ``W + scaling * B @ A`` under ``W``'s HF name, with no adapter entries.
"""

from __future__ import annotations

from collections.abc import Container, Iterator, Mapping

import torch
from torch import nn

from infinirl.engines.sharding import full_tensor
from infinirl.engines.train_base import LoraSettings

__all__ = ["LORA_ADAPTER", "LoraMergePlan", "apply_lora", "changing_weight_names", "hf_name", "lora_merge_plan",
           "merged_full_weights"]

LORA_ADAPTER = "default"  # peft's name of the one adapter we add
_PEFT_PREFIX = "base_model.model."

#: ``{module FQN: (scaling, fan_in_fan_out)}`` of every LoRA-wrapped linear layer.
LoraMergePlan = dict[str, tuple[float, bool]]


def apply_lora(model: nn.Module, settings: LoraSettings, fully_trained: list[str] | None = None) -> nn.Module:
    """Wrap ``model`` with LoRA adapters; modules named in ``fully_trained`` (a critic's freshly
    initialised value head) get no adapter and train in full (peft's ``modules_to_save``)."""
    from peft import LoraConfig, get_peft_model
    from peft.tuners.lora import Linear as LoraLinear
    from peft.tuners.lora import LoraLayer

    layers = None
    if settings.top_layers:
        total = int(model.config.num_hidden_layers)
        if not 0 < settings.top_layers <= total:
            raise ValueError(f"lora.top_layers={settings.top_layers}: the model has {total} decoder layers; "
                             f"use 1..{total}, or 0 for all")
        layers = list(range(total - settings.top_layers, total))
    targets = settings.target_modules
    if layers is not None and targets == "all-linear":  # peft wants explicit names with a layer filter
        skip = {"lm_head", *(fully_trained or [])}
        targets = sorted({name.rsplit(".", 1)[-1] for name, module in model.named_modules()
                          if isinstance(module, nn.Linear) and name.rsplit(".", 1)[-1] not in skip})
    config = LoraConfig(
        r=settings.r,
        lora_alpha=settings.alpha,
        target_modules=targets,
        lora_dropout=settings.dropout,
        bias="none",
        modules_to_save=fully_trained,
        layers_to_transform=layers,
    )
    peft_model = get_peft_model(model, config)
    try:  # a model without input embeddings (or one that does not say) has nothing to tie to
        embedding_weight = getattr(peft_model.get_input_embeddings(), "weight", None)
    except (AttributeError, NotImplementedError):
        embedding_weight = None
    for name, module in peft_model.named_modules():
        if isinstance(module, LoraLayer) and not isinstance(module, LoraLinear):
            raise ValueError(
                f"LoRA target {name!r} is a {type(module).__name__}; only nn.Linear targets are "
                "supported (their merge for weight sync is implemented). Narrow target_modules."
            )
        base_weight = getattr(getattr(module, "base_layer", None), "weight", None)
        if isinstance(module, LoraLayer) and embedding_weight is not None and base_weight is embedding_weight:
            raise ValueError(
                f"LoRA target {name!r} shares its weight with the input embeddings (tie_word_embeddings): the "
                "merged export would change the rollout's embeddings as well, which the trainer's adapter does "
                "not. Leave it out of lora.target_modules (all-linear does)."
            )
    return peft_model


def lora_merge_plan(model: nn.Module) -> LoraMergePlan:
    """What :func:`merged_full_weights` needs to merge each adapter into its base weight."""
    from peft.tuners.lora import LoraLayer

    return {
        name: (float(module.scaling[LORA_ADAPTER]), bool(getattr(module, "fan_in_fan_out", False)))
        for name, module in model.named_modules()
        if isinstance(module, LoraLayer)
    }


def changing_weight_names(model: nn.Module, plan: LoraMergePlan) -> frozenset[str]:
    """The state-dict names of the weights training can change: every trainable parameter but the
    adapters themselves (under each of a tied weight's names), and each LoRA layer's base weight,
    which its adapter is merged into for export. A LoRA run on the top layers changes a fraction
    of the model; the rest is what the rollout already holds."""
    names = {name for name, param in model.named_parameters(remove_duplicate=False)
             if param.requires_grad and ".lora_A." not in name and ".lora_B." not in name}
    return frozenset(names | {f"{module_name}.base_layer.weight" for module_name in plan})


def merged_full_weights(state_dict: Mapping[str, torch.Tensor], plan: LoraMergePlan,
                        dtype: torch.dtype | None = None,
                        only: Container[str] | None = None) -> Iterator[tuple[str, torch.Tensor]]:
    """``(HF name, full tensor)`` of every entry of a (possibly sharded, possibly LoRA) state dict,
    or of the entries named in ``only`` (state-dict names, e.g. :func:`changing_weight_names`).

    Each sharded tensor is gathered on its own (a collective: every rank must consume the iterator
    to the end), so peak memory is one full parameter. Adapters are merged into their base
    weights and not yielded themselves; ``dtype`` casts.
    """
    for name, tensor in state_dict.items():
        if plan and (".lora_A." in name or ".lora_B." in name):
            continue
        if only is not None and name not in only:
            continue
        full = full_tensor(tensor.detach())
        module_name, _, leaf = name.rpartition(".base_layer.")
        if leaf == "weight" and module_name in plan:
            full = full + _lora_delta(state_dict, module_name, plan)
        yield hf_name(name), (full.to(dtype) if dtype is not None else full)


def _lora_delta(state_dict: Mapping[str, torch.Tensor], module_name: str, plan: LoraMergePlan) -> torch.Tensor:
    scaling, fan_in_fan_out = plan[module_name]
    lora_a = full_tensor(state_dict[f"{module_name}.lora_A.{LORA_ADAPTER}.weight"].detach())
    lora_b = full_tensor(state_dict[f"{module_name}.lora_B.{LORA_ADAPTER}.weight"].detach())
    delta = (lora_b @ lora_a) * scaling
    return delta.T if fan_in_fan_out else delta


def hf_name(name: str) -> str:
    """peft's wrapped name -> the plain HF model's state_dict key."""
    if name.startswith(_PEFT_PREFIX):
        name = name[len(_PEFT_PREFIX):]
    return name.replace(".base_layer.", ".")
