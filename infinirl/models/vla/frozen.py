"""What the policies that keep a flow VLA frozen share (:mod:`~infinirl.models.vla.steered`,
:mod:`~infinirl.models.vla.residual`): small MLPs on the VLA's features train, the VLA acts with
its deterministic sampler, and the features travel with the batch so the trainer's update never
runs the VLA."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from infinirl.models.vla.policy import pooled_prefix

__all__ = ["FrozenVLA", "mlp"]


def mlp(width: int, hidden: Sequence[int], out: int, zero_last: bool = False) -> nn.Sequential:
    """SiLU MLP ``width -> hidden... -> out``; ``zero_last`` zeroes the output layer (a head that
    starts at 0, so the policy starts as the VLA)."""
    layers: list[nn.Module] = []
    for size in hidden:
        layers += [nn.Linear(width, size), nn.SiLU()]
        width = size
    layers.append(nn.Linear(width, out))
    if zero_last:
        nn.init.zeros_(layers[-1].weight)
        nn.init.zeros_(layers[-1].bias)
    return nn.Sequential(*layers)


class FrozenVLA:
    """Mixin for a :class:`~infinirl.models.vla.policy.PiZeroPolicy` subclass whose VLA does not
    train. Call :meth:`_freeze` in ``__init__`` after the VLA policy's own."""

    critic_modules = ("value_net",)
    lora_refusal = "the VLA is frozen and the update never runs it, so adapters on it would not train"

    def _freeze(self) -> int:
        """Freezes the VLA; returns the width of :meth:`features`."""
        self.vla.requires_grad_(False)
        config = self.vla.config
        return config.architecture.vlm.width + config.max_state_dim

    @torch.no_grad()
    def features(self, obs) -> tuple[torch.Tensor, object, object]:
        """``[B, width + max_state_dim]``: the mean prefix hidden state and the normalised state
        (zeros where the family tokenises its state); also the inputs and the prefix."""
        x = self.inputs(obs)
        prefix = self._prefix(x)
        pooled = pooled_prefix(prefix.hidden, prefix.pad_mask)
        width = self.vla.config.max_state_dim
        state = (x.state.float().reshape(len(pooled), -1)[:, :width] if x.state is not None
                 else torch.zeros(len(pooled), width, device=pooled.device))
        return torch.cat([pooled, state], dim=-1), x, prefix

    @torch.no_grad()
    def decode(self, x, prefix, noise: torch.Tensor) -> torch.Tensor:
        """The VLA's deterministic sampler from ``noise`` ``[B, chunk_size, max_action_dim]``: the
        env's action chunk ``[B, chunk, action_dim]``."""
        current = noise.float()
        for k in range(self.num_steps):
            _, _, current = self.transition(prefix, x.state, current, k)
        return self.vla.processor.actions_out(current)[:, :self.chunk, :self.action_dim]

    def _critic(self, features: torch.Tensor) -> torch.Tensor | None:
        return None if self.value_net is None else self.value_net(features).squeeze(-1)
