"""Latent-noise steering of a flow VLA: RL trains a small policy over the *initial noise* ``x_0`` of
the frozen VLA's deterministic sampler (DSRL, Wagenmaker et al. 2025, "Steering Your Diffusion
Policy with Latent Space Reinforcement Learning").

A flow policy's noise-free action still starts from a noise draw: which draw decides, on many
layouts, whether the cloned policy succeeds (docs/results.md, the 30-episode evaluation's noise).
Steering learns, per observation, where to draw it: ``x_0 ~ N(mu(s), sigma^2)`` over the VLA's
whole chunk ``[chunk_size, max_action_dim]``; the VLA's Euler sampler (π0's own, step for step)
turns ``x_0`` into the action chunk. The VLA stays bit for bit as cloned, so every action is one
the cloned policy could take; what RL changes is which of them it takes.

* ``mu`` is a small MLP on the VLA's features (the mean of the VLM's prefix hidden states and the
  normalised state), its last layer zero: at the start ``x_0 ~ N(0, sigma^2)`` with ``sigma = 1``
  is the VLA's own sampling, so RL starts from the cloned policy. ``sigma`` is a learned vector.
* PPO's log-probs and entropy are those of ``x_0`` (its Gaussian density, summed over the chunk's
  noise dims), credited to the chunk's first action (one decision; the chunk's other entries are
  zero). The critic is an MLP on the same features.
* The features and ``x_0`` travel with the batch (``extras``): the VLA is frozen, so the trainer's
  update is the two MLPs alone, without a VLM forward pass: updates cost almost nothing, and the
  time goes into acting.
* Acting deterministically uses ``x_0 = mu(s)``.
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

__all__ = ["NoiseSteering", "PiZeroFiveSteeredPolicy", "PiZeroSmolLM2SteeredPolicy", "PiZeroSteeredPolicy"]


class NoiseSteering(FrozenVLA):
    """Turns a :class:`~infinirl.models.vla.policy.PiZeroPolicy` subclass into its steered form.

    Args (besides the VLA policy's; its flow-SDE options do not apply):
        noise_hidden: the noise policy's and the critic's hidden widths.
        noise_std: ``sigma`` at the start (1: the VLA's own noise).
        noise_bound: ``mu`` is ``noise_bound * tanh(.)``: the VLA has only seen noise near the
            standard normal's bulk, so the mean stays within a few standard deviations of it.
        critic_obs: an observation field the critic alone also reads (:class:`FrozenVLA`);
            ``critic_obs_dim`` its size (filled from the env's spec by the embodied runner).
    """

    demo_refusal = "the VLA is frozen and only the noise policy trains, which demonstrations do not label"

    def __init__(self, *args, noise_hidden: Sequence[int] = (256, 256), noise_std: float = 1.0,
                 noise_bound: float = 2.5, critic_obs: str | None = None, critic_obs_dim: int | None = None,
                 value_head: bool = True, **kwargs):
        if noise_std <= 0 or noise_bound <= 0:
            raise ValueError(f"noise_std and noise_bound must be > 0, got {noise_std} and {noise_bound}")
        super().__init__(*args, value_head=False, **kwargs)
        features = self._freeze()
        config = self.vla.config
        self.noise_shape = (config.chunk_size, config.max_action_dim)
        size = math.prod(self.noise_shape)
        self.noise_net = mlp(features, noise_hidden, size, zero_last=True)
        self.noise_log_std = nn.Parameter(torch.full((size,), math.log(noise_std)))
        self.noise_bound = float(noise_bound)
        self.has_value_head = value_head
        critic_width = features + self._privileged_width(critic_obs, critic_obs_dim)
        self.value_net = mlp(critic_width, noise_hidden, 1) if value_head else None

    # --- the noise distribution --------------------------------------------------

    def noise_distribution(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``mu`` ``[B, chunk_size * max_action_dim]`` and ``log sigma`` (broadcast to it)."""
        mean = self.noise_bound * torch.tanh(self.noise_net(features) / self.noise_bound)
        return mean, self.noise_log_std.expand_as(mean)

    def _per_decision(self, values: torch.Tensor) -> torch.Tensor:
        """``[B]`` -> ``[B, chunk]``: the whole decision's number on its first action."""
        out = torch.zeros(values.shape[0], self.chunk, dtype=values.dtype, device=values.device)
        out[:, 0] = values
        return out

    # --- the Policy interface ----------------------------------------------------------------

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        features, x, prefix = self.features(obs)
        with torch.no_grad():
            mean, log_std = self.noise_distribution(features)
            flat = mean if deterministic else mean + log_std.exp() * torch.randn_like(mean)
            logprobs = gaussian_logprob(flat, mean, log_std).sum(-1)
            values = self._critic(features, obs)
        actions = self.decode(x, prefix, flat.reshape(-1, *self.noise_shape))
        return PolicyStep(actions=actions, logprobs=self._per_decision(logprobs), values=values,
                          extras={"noise": flat, "features": features})

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        """Log-probs of the recorded noise under the present noise policy: the two MLPs on the
        recorded features, no VLA pass."""
        if not extras or "noise" not in extras or "features" not in extras:
            raise ValueError("a steered VLA's evaluate needs extras['noise'] and extras['features'] from act()")
        features = extras["features"].detach().float()
        mean, log_std = self.noise_distribution(features)
        logprobs = self._per_decision(gaussian_logprob(extras["noise"].detach().float(), mean, log_std).sum(-1))
        entropy = self._per_decision(gaussian_entropy(log_std).sum(-1)) if with_entropy else None
        return PolicyEval(logprobs=logprobs, entropy=entropy, values=self._critic(features, obs))

    def value(self, obs) -> torch.Tensor:
        if self.value_net is None:
            raise NotImplementedError("this steered VLA was built with value_head=False")
        return self._critic(self.features(obs)[0], obs)


@POLICIES.register("pi0_steered")
class PiZeroSteeredPolicy(NoiseSteering, PiZeroPolicy):
    """A π0 checkpoint steered through its initial noise (:mod:`infinirl.models.vla.steered`)."""


@POLICIES.register("pi05_steered")
class PiZeroFiveSteeredPolicy(NoiseSteering, PiZeroFivePolicy):
    """A π0.5 checkpoint steered through its initial noise."""


@POLICIES.register("pi0_smollm2_steered")
class PiZeroSmolLM2SteeredPolicy(NoiseSteering, PiZeroSmolLM2Policy):
    """The small ``pi0_smollm2`` VLA steered through its initial noise."""
