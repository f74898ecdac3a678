"""Residual RL on a frozen flow VLA: RL trains a small Gaussian policy whose action chunk is *added*
to the VLA's noise-free chunk (ResiP, Ankile et al. 2024, "From Imitation to Refinement"; Policy
Decorator, Yuan et al. 2024).

Steering (:mod:`~infinirl.models.vla.steered`) can only pick among the chunks the cloned VLA can
produce; a cloned policy that is *stuck* (docs/results.md: most of its failures on the demo are
stuck, not slow) may need an action none of them is. The residual acts in the env's action space
directly, close to the cloned behaviour:

* the base chunk ``b(s)`` is the VLA's deterministic sampler from noise 0 (its noise's mean);
* the residual ``r ~ N(mu(s, b), sigma^2)`` per action and dim, ``mu = residual_bound *
  tanh(f(s, b) / residual_bound)`` with ``f`` a small MLP whose last layer starts at zero, so the
  noise-free policy starts exactly as the VLA's noise-free one and the sampled one near it;
  ``sigma`` is a learned vector, one per action dim (``residual_std`` at the start);
* the action is ``b(s) + r``; ``f`` and the critic read the VLA's features (mean prefix hidden
  state, normalised state) and the base chunk, which travel with the batch (``extras``): the
  trainer's update runs the two MLPs only, never the VLA.

PPO's log-probs are per executed action (the chunk's actions are independent given ``s``), the
Gaussian densities of the recorded residual.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from infinirl.models.policies.base import POLICIES, PolicyEval, PolicyStep
from infinirl.models.policies.heads import gaussian_entropy
from infinirl.models.policies.mlp import gaussian_logprob
from infinirl.models.vla.frozen import FrozenVLA, mlp
from infinirl.models.vla.policy import PiZeroFivePolicy, PiZeroPolicy, PiZeroSmolLM2Policy

__all__ = ["PiZeroFiveResidualPolicy", "PiZeroResidualPolicy", "PiZeroSmolLM2ResidualPolicy", "ResidualCorrection"]


class ResidualCorrection(FrozenVLA):
    """Turns a :class:`~infinirl.models.vla.policy.PiZeroPolicy` subclass into its residual form.

    Args (besides the VLA policy's; its flow-SDE options do not apply):
        residual_hidden: the residual policy's and the critic's hidden widths.
        residual_std: ``sigma`` at the start, in the env's action units.
        residual_bound: the largest residual mean per dim (``tanh`` squashed).
    """

    demo_refusal = "the VLA is frozen and only the residual policy trains, which demonstrations do not label"

    def __init__(self, *args, residual_hidden: Sequence[int] = (256, 256), residual_std: float = 0.2,
                 residual_bound: float = 1.0, value_head: bool = True, **kwargs):
        if residual_std <= 0 or residual_bound <= 0:
            raise ValueError(f"residual_std and residual_bound must be > 0, got {residual_std} and {residual_bound}")
        super().__init__(*args, value_head=False, **kwargs)
        features = self._freeze() + self.chunk * self.action_dim
        self.residual_net = mlp(features, residual_hidden, self.chunk * self.action_dim, zero_last=True)
        self.residual_log_std = nn.Parameter(torch.full((self.action_dim,), math.log(residual_std)))
        self.residual_bound = float(residual_bound)
        self.has_value_head = value_head
        self.value_net = mlp(features, residual_hidden, 1) if value_head else None

    def base(self, obs) -> tuple[torch.Tensor, torch.Tensor]:
        """The VLA's noise-free chunk ``[B, chunk, action_dim]`` and the residual policy's input
        ``[B, features + chunk * action_dim]``."""
        features, x, prefix = self.features(obs)
        config = self.vla.config
        noise = torch.zeros(len(features), config.chunk_size, config.max_action_dim, device=features.device)
        base = self.decode(x, prefix, noise)
        return base, torch.cat([features, base.reshape(len(base), -1)], dim=-1)

    def residual_distribution(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``mu`` ``[B, chunk, action_dim]`` and ``log sigma`` (broadcast to it)."""
        raw = self.residual_net(inputs).reshape(-1, self.chunk, self.action_dim)
        mean = self.residual_bound * torch.tanh(raw / self.residual_bound)
        return mean, self.residual_log_std.expand_as(mean)

    # --- the Policy interface ----------------------------------------------------------------

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        base, inputs = self.base(obs)
        with torch.no_grad():
            mean, log_std = self.residual_distribution(inputs)
            residual = mean if deterministic else mean + log_std.exp() * torch.randn_like(mean)
            logprobs = gaussian_logprob(residual, mean, log_std).sum(-1)
            values = self._critic(inputs)
        return PolicyStep(actions=base + residual, logprobs=logprobs, values=values,
                          extras={"residual": residual, "features": inputs})

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        """Log-probs of the recorded residual under the present residual policy: the two MLPs on
        the recorded features, no VLA pass."""
        if not extras or "residual" not in extras or "features" not in extras:
            raise ValueError("a residual VLA's evaluate needs extras['residual'] and extras['features'] from act()")
        inputs = extras["features"].detach().float()
        mean, log_std = self.residual_distribution(inputs)
        logprobs = gaussian_logprob(extras["residual"].detach().float(), mean, log_std).sum(-1)
        entropy = gaussian_entropy(log_std).sum(-1) if with_entropy else None
        return PolicyEval(logprobs=logprobs, entropy=entropy, values=self._critic(inputs))

    def value(self, obs) -> torch.Tensor:
        if self.value_net is None:
            raise NotImplementedError("this residual VLA was built with value_head=False")
        return self._critic(self.base(obs)[1])


@POLICIES.register("pi0_residual")
class PiZeroResidualPolicy(ResidualCorrection, PiZeroPolicy):
    """A π0 checkpoint with a residual policy on its actions (:mod:`infinirl.models.vla.residual`)."""


@POLICIES.register("pi05_residual")
class PiZeroFiveResidualPolicy(ResidualCorrection, PiZeroFivePolicy):
    """A π0.5 checkpoint with a residual policy on its actions."""


@POLICIES.register("pi0_smollm2_residual")
class PiZeroSmolLM2ResidualPolicy(ResidualCorrection, PiZeroSmolLM2Policy):
    """The small ``pi0_smollm2`` VLA with a residual policy on its actions."""
