"""MLP Gaussian policy on low-dimensional state, with an optional value head.

The action distribution is a diagonal Gaussian in the *unsquashed* space with a state-independent
log-std (the cleanRL/PPO default that learns fastest on MetaWorld-style tasks); envs clip actions to
their box. Log-probs are of the unclipped sample, which is what PPO's ratio needs.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from infinirl.models.policies.base import POLICIES, Policy, PolicyEval, PolicyStep


def mlp(sizes: list[int], activation: type[nn.Module] = nn.Tanh, out_gain: float = 1.0) -> nn.Sequential:
    """Orthogonally initialised MLP (gain sqrt(2) hidden, ``out_gain`` last), as in PPO practice."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        linear = nn.Linear(sizes[i], sizes[i + 1])
        last = i == len(sizes) - 2
        nn.init.orthogonal_(linear.weight, out_gain if last else math.sqrt(2))
        nn.init.zeros_(linear.bias)
        layers.append(linear)
        if not last:
            layers.append(activation())
    return nn.Sequential(*layers)


def gaussian_logprob(x: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """Elementwise log N(x; mean, exp(log_std)^2)."""
    return -((x - mean) ** 2) / (2 * torch.exp(2 * log_std)) - log_std - 0.5 * math.log(2 * math.pi)


@POLICIES.register("mlp_gaussian")
class MLPGaussianPolicy(Policy):
    """``obs[obs_key]`` -> Gaussian over a chunk of ``chunk`` actions of ``action_dim`` dims."""

    critic_modules = ("critic",)

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...] = (64, 64), chunk: int = 1,
                 init_log_std: float = 0.0, value_head: bool = True, obs_key: str = "state"):
        super().__init__()
        self.action_dim, self.chunk, self.obs_key = action_dim, chunk, obs_key
        self.actor = mlp([obs_dim, *hidden, action_dim * chunk], out_gain=0.01)
        self.log_std = nn.Parameter(torch.full((action_dim * chunk,), float(init_log_std)))
        self.has_value_head = value_head
        self.critic = mlp([obs_dim, *hidden, 1], out_gain=1.0) if value_head else None

    def _obs(self, obs) -> torch.Tensor:
        # Cast to the parameters' dtype (not a fixed float32), so .double()/bf16 policies work.
        return obs[self.obs_key].to(self.log_std.dtype)

    def _mean(self, obs) -> torch.Tensor:
        return self.actor(self._obs(obs))

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        mean = self._mean(obs)
        log_std = self.log_std.expand_as(mean)
        actions = mean if deterministic else mean + torch.randn_like(mean) * log_std.exp()
        logprobs = gaussian_logprob(actions, mean, log_std)
        batch = mean.shape[0]
        return PolicyStep(
            actions=actions.view(batch, self.chunk, self.action_dim),
            logprobs=logprobs.view(batch, self.chunk, self.action_dim).sum(-1),
            values=self.value(obs) if self.has_value_head else None,
        )

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        mean = self._mean(obs)
        batch = mean.shape[0]
        log_std = self.log_std.expand_as(mean)
        # Actions are data here (detached): scored as given, never differentiated through (act's
        # reparameterised samples would otherwise cancel the mean's and log-std's gradients).
        logprobs = gaussian_logprob(actions.detach().reshape(batch, -1), mean, log_std)
        entropy = None
        if with_entropy:
            entropy = (0.5 + 0.5 * math.log(2 * math.pi) + log_std).view(batch, self.chunk, self.action_dim).sum(-1)
        return PolicyEval(
            logprobs=logprobs.view(batch, self.chunk, self.action_dim).sum(-1),
            entropy=entropy,
            values=self.value(obs) if self.has_value_head else None,
        )

    def value(self, obs) -> torch.Tensor:
        if self.critic is None:
            raise NotImplementedError("MLPGaussianPolicy was built with value_head=False")
        return self.critic(self._obs(obs)).squeeze(-1)
