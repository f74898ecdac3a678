"""SAC's networks: a tanh-squashed Gaussian actor and an ensemble of Q critics.

**Actor** (:class:`SquashedGaussianActor`, Haarnoja et al. 2018, appendix C). An MLP gives the
mean and log-std of a diagonal Gaussian over ``u``; the action is ``a = tanh(u)`` in ``[-1, 1]^A``
(the env's box is reached by the affine map :meth:`SquashedGaussianActor.to_env`). The log-density
of ``a`` includes the change of variables::

    log pi(a|s) = sum_i [ log N(u_i; mu_i, sigma_i) - log(1 - tanh(u_i)^2) ]

with ``log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))`` (exact, and stable for large ``|u|``).
The affine map to the env's box adds a constant ``-sum log(scale)``, which we leave out: SAC's
losses see it only through ``alpha * log pi`` and the target entropy, and keeping log-probs in the
normalised space makes ``target_entropy = -A`` mean the same for every action range. The log-std
is squashed into ``[log_std_min, log_std_max]`` with a tanh (as in cleanRL), which keeps the
gradient alive at the bounds.

Sampling is reparameterised (``u = mu + sigma * eps``) so the actor loss differentiates through
the action into the critics; noise comes from an explicit ``torch.Generator`` when given, so the
collector's and the learner's random streams are their own and are checkpointed.

**Critics** (:class:`EnsembleQ`). ``K`` independent Q-networks stored as stacked weights
``[K, in, out]`` and evaluated with one batched matmul per layer (``torch.baddbmm``), instead of
``K`` separate modules: the same maths (each critic has its own initialisation and parameters),
a third of the kernel launches on CPU for the usual ``K = 2``. ``forward`` returns ``[K, B]``, the
layout :mod:`infinirl.algorithms.sac` takes.

Observations are a low-dimensional vector (``obs[obs_key]``, default ``state``); for camera frames an
encoder sits in front of both (:mod:`infinirl.models.sac_encoders`) and these networks take its features.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["EnsembleLayerNorm", "EnsembleLinear", "EnsembleQ", "FlowSACActor", "SquashedGaussianActor",
           "squash_logprob_correction"]

_LOG2 = math.log(2.0)


def squash_logprob_correction(u: torch.Tensor) -> torch.Tensor:
    """``log(1 - tanh(u)^2)`` elementwise, computed stably."""
    return 2.0 * (_LOG2 - u - F.softplus(-2.0 * u))


def _activation(name: str) -> type[nn.Module]:
    table = {"relu": nn.ReLU, "tanh": nn.Tanh, "silu": nn.SiLU, "elu": nn.ELU}
    if name not in table:
        raise ValueError(f"activation must be one of {sorted(table)}, got {name!r}")
    return table[name]


class SquashedGaussianActor(nn.Module):
    """``obs -> tanh(N(mu(obs), sigma(obs)))`` over ``action_dim`` dims in ``[-1, 1]``.

    Args:
        obs_dim / action_dim: input and action sizes.
        low / high: the env's action box (per dim); used only by :meth:`to_env`.
        hidden: hidden layer sizes of the MLP trunk.
        log_std_min / log_std_max: range of the log standard deviation.
        activation: ``relu`` (SAC's default), ``tanh``, ``silu`` or ``elu``.
        obs_key: which observation field is the input vector.
        layer_norm: a LayerNorm after each hidden linear layer, before the activation.
    """

    def __init__(self, obs_dim: int, action_dim: int, low: Sequence[float], high: Sequence[float],
                 hidden: Sequence[int] = (256, 256), log_std_min: float = -5.0, log_std_max: float = 2.0,
                 activation: str = "relu", obs_key: str = "state", layer_norm: bool = False):
        super().__init__()
        if not log_std_min < log_std_max:
            raise ValueError(f"log_std_min ({log_std_min}) must be < log_std_max ({log_std_max})")
        act = _activation(activation)
        layers: list[nn.Module] = []
        size = obs_dim
        for width in hidden:
            layers += [nn.Linear(size, width), *([nn.LayerNorm(width)] if layer_norm else []), act()]
            size = width
        self.trunk = nn.Sequential(*layers)
        self.mean = nn.Linear(size, action_dim)
        self.log_std = nn.Linear(size, action_dim)
        self.action_dim, self.obs_key = action_dim, obs_key
        self.log_std_min, self.log_std_max = float(log_std_min), float(log_std_max)
        low_t = torch.as_tensor(low, dtype=torch.float32).reshape(action_dim)
        high_t = torch.as_tensor(high, dtype=torch.float32).reshape(action_dim)
        if not torch.isfinite(low_t).all() or not torch.isfinite(high_t).all() or (high_t <= low_t).any():
            raise ValueError(f"SAC needs a bounded action box, got low={low_t.tolist()} high={high_t.tolist()}")
        # Buffers, not parameters: they go with state_dict (so a checkpoint is self-contained) but
        # are never trained.
        self.register_buffer("action_scale", (high_t - low_t) / 2.0)
        self.register_buffer("action_bias", (high_t + low_t) / 2.0)

    def distribution(self, obs: dict[str, torch.Tensor] | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of the pre-squash Gaussian, each ``[B, A]``."""
        x = obs[self.obs_key] if isinstance(obs, dict) else obs
        features = self.trunk(x.to(self.mean.weight.dtype))
        mean = self.mean(features)
        log_std = torch.tanh(self.log_std(features))
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (log_std + 1.0)
        return mean, log_std

    masks_logprob = True
    """:meth:`sample` takes a ``mask`` of the action entries its log-probability sums over."""

    def sample(self, obs, generator: torch.Generator | None = None, deterministic: bool = False,
               mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(action in [-1, 1], log pi(action|obs) [B], pre-squash u)``, reparameterised.

        ``deterministic`` returns ``tanh(mu)`` (evaluation); its log-prob is that of ``u = mu``.
        ``mask`` ``[B, A]`` (0/1): the log-prob of the entries it keeps, the marginal of the
        independent per-entry distribution (padding entries a robot does not execute drop out).
        """
        mean, log_std = self.distribution(obs)
        if deterministic:
            u = mean
        else:
            # Drawn where the generator lives (SAC's is on the CPU) and copied to the network's
            # device: the same noise on a CPU and a GPU learner.
            draw_on = generator.device if generator is not None else mean.device
            noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=draw_on).to(mean.device)
            u = mean + log_std.exp() * noise
        return torch.tanh(u), self._logprob(u, mean, log_std, mask), u

    def logprob_of(self, obs, u: torch.Tensor) -> torch.Tensor:
        """``log pi(tanh(u)|obs)`` ``[B]`` for given pre-squash samples ``u`` (diagnostics: the
        learner re-scores the collector's samples to check that both hold the same weights)."""
        mean, log_std = self.distribution(obs)
        return self._logprob(u.to(mean.dtype), mean, log_std)

    @staticmethod
    def _logprob(u: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor,
                 mask: torch.Tensor | None = None) -> torch.Tensor:
        gaussian = -0.5 * ((u - mean) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
        terms = gaussian - squash_logprob_correction(u)
        return (terms if mask is None else terms * mask.to(terms.dtype)).sum(-1)

    def to_env(self, action: torch.Tensor) -> torch.Tensor:
        """``[-1, 1]`` actions -> the env's box."""
        return action * self.action_scale + self.action_bias


class EnsembleLinear(nn.Module):
    """``K`` independent linear layers applied to ``[K, B, in]`` at once (``[K, B, out]``).

    Each member is initialised like ``nn.Linear`` (Kaiming-uniform weights, uniform bias in
    ``+-1/sqrt(in)``), independently.
    """

    def __init__(self, num_members: int, in_features: int, out_features: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(num_members, in_features, out_features))
        self.bias = nn.Parameter(torch.empty(num_members, 1, out_features))
        bound = 1.0 / math.sqrt(in_features)
        for k in range(num_members):  # same scheme as nn.Linear.reset_parameters, per member
            weight_k = torch.empty(out_features, in_features)
            nn.init.kaiming_uniform_(weight_k, a=math.sqrt(5))
            self.weight.data[k] = weight_k.t()
            nn.init.uniform_(self.bias.data[k], -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class EnsembleLayerNorm(nn.Module):
    """``K`` independent LayerNorms over the last dim of ``[K, B, width]`` (each its own gain and bias)."""

    def __init__(self, num_members: int, width: int):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(num_members, 1, width))
        self.bias = nn.Parameter(torch.zeros(num_members, 1, width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.layer_norm(x, x.shape[-1:]) * self.weight + self.bias


class EnsembleQ(nn.Module):
    """``K`` Q-networks ``Q_k(obs, action)``; ``forward`` returns ``[K, B]``.

    Actions are the actor's ``[-1, 1]`` actions (the normalised space), so the critics' inputs have
    the same scale whatever the env's action range. ``layer_norm``: a LayerNorm after each hidden
    layer, which keeps Q from diverging when many updates are made per sample (Ball et al. 2023,
    RLPD; DSRL's critics).
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden: Sequence[int] = (256, 256), num_critics: int = 2,
                 activation: str = "relu", obs_key: str = "state", layer_norm: bool = False):
        super().__init__()
        if num_critics < 1:
            raise ValueError(f"num_critics must be >= 1, got {num_critics}")
        self.num_critics, self.obs_key = num_critics, obs_key
        sizes = [obs_dim + action_dim, *hidden, 1]
        self.layers = nn.ModuleList(EnsembleLinear(num_critics, a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.norms = (nn.ModuleList(EnsembleLayerNorm(num_critics, width) for width in hidden) if layer_norm
                      else None)
        self.act = _activation(activation)()

    def forward(self, obs, action: torch.Tensor) -> torch.Tensor:
        x = obs[self.obs_key] if isinstance(obs, dict) else obs
        x = torch.cat([x.to(action.dtype), action], dim=-1)
        x = x.unsqueeze(0).expand(self.num_critics, *x.shape)
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = self.act(x if self.norms is None else self.norms[i](x))
        return x.squeeze(-1)


class FlowSACActor(nn.Module):
    """SAC-Flow: the registered ``flow_matching`` policy as SAC's actor, squashed by ``tanh``.

    The flow policy samples an action by ``N`` denoising steps, each a Gaussian transition
    ``x_{k+1} = mean_k(x_k) + std_k(x_k) eps_k`` (see :mod:`infinirl.models.policies.flow`). With the
    noise drawn first, the whole chain is a differentiable function of the parameters, so the
    sample is **reparameterised**: SAC's actor loss back-propagates through every denoising step
    into the velocity network (the "flow as a sequential model" view of SAC Flow, Zhang et al.
    2025). The log-probability SAC needs is replaced by the **path log-density** the flow policy
    reports, ``sum_k log N(x_{k+1}; mean_k, std_k)``, plus the tanh change of variables on the last
    state. That is the joint density of the denoising path given the starting noise ``x_0``, not the
    marginal density of the action (which a flow does not give in closed form), so
    ``-E[log pi]`` here is the entropy of the path, and the temperature tunes *that* towards
    ``target_entropy``; see docs/sac.md for what this does and does not guarantee.

    Use ``noise_method="flow_noise"`` (a learned, state-dependent std per step): under
    reparameterisation each step's term is ``-eps^2/2 - log std_k`` and only a learned std makes the
    entropy bonus act on the policy. With ``flow_sde`` the std is fixed by the schedule, the path
    log-prob is a constant, and SAC degenerates to a deterministic-gradient actor with fixed noise.

    Randomness: the flow policy draws from torch's global generator, so each call forks it and
    seeds it from ``generator`` (SAC's own stream), keeping runs reproducible and resumable.
    """

    def __init__(self, obs_dim: int, action_dim: int, low: Sequence[float], high: Sequence[float],
                 obs_key: str = "state", **flow_kwargs):
        super().__init__()
        from infinirl.models.policies.base import build_policy

        options = {"num_steps": 4, "noise_method": "flow_noise", "hidden": (128, 128), **flow_kwargs,
                   "value_head": False, "chunk": 1}
        self.flow = build_policy("flow_matching", action_dim=action_dim, obs_dim=obs_dim, obs_key=obs_key, **options)
        self.action_dim, self.obs_key = action_dim, obs_key
        low_t = torch.as_tensor(low, dtype=torch.float32).reshape(action_dim)
        high_t = torch.as_tensor(high, dtype=torch.float32).reshape(action_dim)
        self.register_buffer("action_scale", (high_t - low_t) / 2.0)
        self.register_buffer("action_bias", (high_t + low_t) / 2.0)

    masks_logprob = False
    """The path log-density does not split by action entry: no ``mask`` (padding entries of a
    multi-robot policy stay in it; the critics still ignore them)."""

    def sample(self, obs, generator: torch.Generator | None = None,
               deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = obs[self.obs_key] if isinstance(obs, dict) else obs
        seed = int(torch.randint(0, 2**62, (1,), generator=generator)) if generator is not None else None
        # fork_rng: the flow draws from torch's global generator of x's device; seeding it here
        # must not disturb anybody else's stream (on CUDA the device's generator is forked too).
        with torch.random.fork_rng(devices=[x.device] if x.device.type == "cuda" else []):
            if seed is not None:
                torch.manual_seed(seed)
            step = self.flow.act({self.obs_key: x.to(self.action_scale.dtype)}, deterministic=deterministic)
        u = step.actions.reshape(x.shape[0], self.action_dim)
        logprob = step.logprobs.reshape(x.shape[0], -1).sum(-1) - squash_logprob_correction(u).sum(-1)
        return torch.tanh(u), logprob, u

    def logprob_of(self, obs, u: torch.Tensor) -> torch.Tensor | None:
        """Not available: a flow's path log-density needs the whole denoising path, not just ``u``."""
        return None

    def to_env(self, action: torch.Tensor) -> torch.Tensor:
        return action * self.action_scale + self.action_bias
