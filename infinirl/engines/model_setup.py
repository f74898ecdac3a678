"""The HF model a training role needs: a causal LM (policy, reference) or a critic built from one,
without dropout, and activation checkpointing on request."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from infinirl.engines.train_base import TrainOutput

__all__ = ["disable_dropout", "enable_activation_checkpointing", "pretrained_factory", "value_head_name"]


def disable_dropout(model: nn.Module) -> None:
    """Every dropout of ``model`` set to 0, as TRL's ``disable_dropout_in_model`` does.

    The trainer's forward runs in train mode while the log-probs it is compared with (the rollout's,
    pi_old's, the reference's) come from eval-mode passes: with dropout on (GPT-2, OPT and Phi ship
    with it) the ratios and the KL would be noise even at the first step. Covered: ``nn.Dropout``
    modules, the float rates some models keep on their modules and pass to functional dropout
    (OPT's ``dropout``, Phi's ``attention_dropout``, OPT's ``layerdrop``), and the configs'
    rate fields, read by code that builds modules or attention calls from the config later.
    """
    configs = {}
    for module in model.modules():
        if isinstance(module, nn.Dropout):
            module.p = 0.0
        for name, value in list(vars(module).items()):
            if _is_dropout_rate(name, value):
                setattr(module, name, 0.0)
        config = getattr(module, "config", None)
        if config is not None and hasattr(config, "to_dict"):
            configs[id(config)] = config
    for config in configs.values():
        for name in list(vars(config)):
            if _is_dropout_rate(name, getattr(config, name)):
                setattr(config, name, 0.0)


def _is_dropout_rate(name: str, value) -> bool:
    """A non-zero float/int rate under a dropout-like name (``attn_pdrop``, ``hidden_dropout_prob``,
    ``layerdrop``): module and config fields of this kind are probabilities of dropping."""
    dropout_like = "dropout" in name or name.endswith(("pdrop", "layerdrop"))
    return dropout_like and isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0


def enable_activation_checkpointing(model: nn.Module) -> None:
    """HF gradient checkpointing of every decoder layer, non-reentrant."""
    if not getattr(model, "supports_gradient_checkpointing", False):
        raise ValueError(
            f"activation_checkpointing=True but {type(model).__name__} does not support HF "
            "gradient checkpointing (supports_gradient_checkpointing is False)"
        )
    # Non-reentrant: works with frozen inputs (LoRA) and with FSDP2's hooks; keeps parameter names.
    kwargs = {"use_reentrant": False}
    if hasattr(model, "activation_checkpointing_enable"):  # transformers >= 5 name
        model.activation_checkpointing_enable(activation_checkpointing_kwargs=kwargs)
    else:
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs=kwargs)


def value_head_name(model: nn.Module) -> str:
    """The attribute holding a token-classification model's output layer (``score`` in
    transformers' generic heads, ``classifier`` in some older families)."""
    for name in ("score", "classifier"):
        if isinstance(getattr(model, name, None), nn.Linear):
            return name
    raise ValueError(
        f"{type(model).__name__} has no 'score'/'classifier' linear head; a critic needs a "
        "token-classification model with one output (backbone + scalar value head)"
    )


def pretrained_factory(name_or_path: str, output: TrainOutput, **hf_kwargs) -> Callable[[], nn.Module]:
    """A zero-argument builder of the float32 HF model for ``output`` from a checkpoint.

    With ``output="values"`` the checkpoint (usually the policy's own causal LM) becomes a critic:
    its backbone under a new scalar value head (``AutoModelForTokenClassification`` with one
    label, as verl does), without dropout, and with the head initialised to zero so every value
    starts at 0 (GAE then starts as the plain reward-to-go, not from noise).
    """
    from transformers import AutoConfig, AutoModelForCausalLM, AutoModelForTokenClassification

    def factory() -> nn.Module:
        if output == "logprobs":
            return AutoModelForCausalLM.from_pretrained(name_or_path, dtype=torch.float32, **hf_kwargs)
        config = AutoConfig.from_pretrained(name_or_path, num_labels=1)
        config.classifier_dropout = 0.0  # noise in the regression target's fit: none
        try:
            model = AutoModelForTokenClassification.from_pretrained(
                name_or_path, config=config, dtype=torch.float32, **hf_kwargs
            )
        except ValueError as exc:  # transformers: "Unrecognized configuration class ..."
            raise ValueError(
                f"cannot build a critic from {name_or_path}: transformers has no "
                f"token-classification head for this architecture ({exc})"
            ) from None
        head = getattr(model, value_head_name(model))
        with torch.no_grad():
            head.weight.zero_()
            if head.bias is not None:
                head.bias.zero_()
        return model

    return factory
