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
    train. Call :meth:`_freeze` in ``__init__`` after the VLA policy's own, and
    :meth:`_privileged_width` before building the critic.

    ``critic_obs`` names an observation field (a flat vector, e.g. MetaWorld's full ``state`` with
    the objects' poses) that the critic reads beside the policy's features: an asymmetric
    actor-critic (Pinto et al. 2017). The value only shapes the advantages in training, so the
    policy that acts, from the camera, the instruction and the proprio, is unchanged; a critic that
    sees where the objects are ranks a decision's outcome with far less noise than one that has to
    infer it from the VLA's pooled features.
    """

    critic_modules = ("value_net",)
    critic_obs: str | None = None
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

    def _privileged_width(self, critic_obs: str | None, critic_obs_dim: int | None) -> int:
        """Records ``critic_obs``; the width it adds to the critic's input (0 without it)."""
        if critic_obs is None:
            return 0
        if not critic_obs_dim or critic_obs_dim <= 0:
            raise ValueError(f"critic_obs={critic_obs!r} needs critic_obs_dim, the field's size (the embodied "
                             "runner fills it from the env's observation spec)")
        self.critic_obs, self.critic_obs_dim = critic_obs, int(critic_obs_dim)
        return self.critic_obs_dim

    def _critic(self, features: torch.Tensor, obs=None) -> torch.Tensor | None:
        """The value of ``features`` ``[B, F]``, with ``obs[critic_obs]`` beside them when set."""
        if self.value_net is None:
            return None
        if self.critic_obs is not None:
            if obs is None or self.critic_obs not in obs:
                raise ValueError(f"critic_obs={self.critic_obs!r}: the observation lacks that field")
            extra = torch.as_tensor(obs[self.critic_obs]).to(features.device, torch.float32)
            extra = extra.reshape(len(features), -1)
            if extra.shape[1] != self.critic_obs_dim:
                raise ValueError(f"critic_obs={self.critic_obs!r} has {extra.shape[1]} values, the critic was "
                                 f"built for critic_obs_dim={self.critic_obs_dim}")
            features = torch.cat([features, extra], dim=-1)
        return self.value_net(features).squeeze(-1)
