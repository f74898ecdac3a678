"""The HF model a training role needs: a causal LM (policy, reference) or a critic built from one,
and activation checkpointing on request."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from infinirl.engines.train_base import TrainOutput

__all__ = ["enable_activation_checkpointing", "pretrained_factory", "value_head_name"]


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
