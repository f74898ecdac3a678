"""LoRA on a robot policy (a VLA's backbone), for the embodied actor's PPO/GRPO updates.

A VLA fine-tuned with RL keeps most of its weights: adapters on its linear layers train, so do the
modules named in ``train_fully`` (the value head, new on top of a pretrained model) and the
policy's ``fresh_modules`` (other new heads); everything else is frozen. Adam then keeps state for
the adapters only and the backward pass stops below the lowest trained layer, which is what makes
RL on a large policy fit a small machine.

The rollout holds a plain policy: :func:`merged_policy_weights` folds each adapter into its base
weight (``W + scaling * B @ A``) under the plain module's names, so weight sync, digests and the
rollout see an ordinary state dict. Checkpoints keep the adapted model as it trains (base weights,
adapters and their optimizer state), so a resumed run continues exactly.

The adapters are peft's (``inject_adapter_in_model``: any ``nn.Module``, not only transformers
models), on explicitly listed ``nn.Linear`` layers.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import torch
from torch import nn

from infinirl.config import bounded
from infinirl.engines.lora import LoraMergePlan, lora_merge_plan, merged_full_weights

__all__ = ["PolicyLoraSpec", "apply_policy_lora", "lora_targets", "merged_policy_weights", "trained_fully"]


@dataclass(kw_only=True)
class PolicyLoraSpec:
    """Low-rank adapters on a policy's linear layers (``actor.lora``)."""

    r: int = bounded(16, ge=1)
    """Adapter rank."""
    alpha: float = bounded(32.0, gt=0)
    """The update is ``(alpha / r) * B @ A``."""
    dropout: float = bounded(0.0, ge=0, lt=1)
    """Dropout on the adapter input; keep 0 for PPO (a stochastic forward makes the ratios noisy)."""
    target_modules: list[str] | str = "all-linear"
    """Linear layers that get adapters: ``all-linear``, or names, each the layer's full name or its
    last parts (``q_proj``, ``vlm.layers.0.mlp.up_proj``)."""
    train_fully: list[str] = field(default_factory=lambda: ["value_net"])
    """Modules trained in full and never adapted (each its full name or its last parts): the value
    head by default."""

    def check(self) -> None:
        """Raise ValueError naming the key for settings no policy can take."""
        if self.r < 1:
            raise ValueError(f"actor.lora.r={self.r} must be >= 1")
        if self.alpha <= 0:
            raise ValueError(f"actor.lora.alpha={self.alpha} must be > 0")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"actor.lora.dropout={self.dropout} must be in [0, 1)")
        if isinstance(self.target_modules, str) and self.target_modules != "all-linear":
            raise ValueError(f"actor.lora.target_modules={self.target_modules!r}: give 'all-linear' or a list of "
                             "layer names")


def _under(name: str, modules: Iterable[str]) -> bool:
    """Whether ``name`` lies in one of ``modules``, each given by its full name or by its last
    parts (``value_net`` names ``policy.value_net``: a wrapper may add a prefix)."""
    dotted = f".{name}."
    return any(f".{m}." in dotted for m in modules)


def trained_fully(policy: nn.Module, spec: PolicyLoraSpec) -> list[str]:
    """``spec.train_fully`` and the policy's ``fresh_modules`` (heads new on top of the pretrained
    model; found on any module inside the trainer's wrappers)."""
    fresh = {name for module in policy.modules() for name in getattr(module, "fresh_modules", ())}
    return [*spec.train_fully, *sorted(fresh - set(spec.train_fully))]


def lora_targets(policy: nn.Module, spec: PolicyLoraSpec) -> list[str]:
    """Full names of the linear layers ``spec`` adapts; ValueError naming the key when none match."""
    full = trained_fully(policy, spec)
    linear = [name for name, module in policy.named_modules()
              if isinstance(module, nn.Linear) and not _under(name, full)]
    if spec.target_modules == "all-linear":
        chosen = linear
    else:
        chosen = [name for name in linear if any(name == t or name.endswith("." + t) for t in spec.target_modules)]
    if not chosen:
        shown = ", ".join(linear[:8]) + (", ..." if len(linear) > 8 else "")
        raise ValueError(f"actor.lora.target_modules={spec.target_modules!r} matches no linear layer of the policy "
                         f"outside train_fully; its linear layers: {shown or 'none'}")
    return chosen


def apply_policy_lora(policy: nn.Module, spec: PolicyLoraSpec) -> LoraMergePlan:
    """Put adapters on ``policy`` in place and freeze what does not train; the merge plan of its
    adapters (what :func:`merged_policy_weights` needs)."""
    from peft import LoraConfig, inject_adapter_in_model

    spec.check()
    targets = lora_targets(policy, spec)
    missing = [p for p in spec.train_fully if not any(_under(n, [p]) for n, _ in policy.named_parameters())]
    if missing:
        raise ValueError(f"actor.lora.train_fully names {missing}, which hold no parameter of the policy")
    config = LoraConfig(r=spec.r, lora_alpha=spec.alpha, lora_dropout=spec.dropout, target_modules=targets,
                        bias="none")
    inject_adapter_in_model(config, policy)
    full = trained_fully(policy, spec)
    for name, parameter in policy.named_parameters():
        parameter.requires_grad_(".lora_A." in name or ".lora_B." in name or _under(name, full))
    return lora_merge_plan(policy)


def merged_policy_weights(weights: Iterable[tuple[str, torch.Tensor]],
                          plan: LoraMergePlan) -> Iterator[tuple[str, torch.Tensor]]:
    """``(name, tensor)`` of the plain policy: adapters folded into their base weights."""
    return merged_full_weights(dict(weights), plan)
