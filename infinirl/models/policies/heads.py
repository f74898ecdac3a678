"""Building blocks shared by the policy families: observation encoders, action heads, value heads.

Nothing here is registered; :mod:`cnn` and :mod:`flow` compose these pieces into policies.

* :class:`ConvEncoder`: a small Nature-DQN-style conv stack for ``rgb`` uint8 ``[B, H, W, C]``
  images (normalised to ``[0, 1]`` inside), fast enough on a CPU for 64x64 / 84x84 inputs.
* :class:`ObsEncoder`: image features and/or a low-dimensional vector (``proprio`` / ``state``),
  concatenated into one feature vector.
* :class:`GaussianHead`: diagonal Gaussian over a chunk of ``K`` actions of ``A`` dims.
* :class:`BinsHead`: each action dim discretised into ``num_bins`` bins over ``[low, high]``;
  one categorical per (chunk step, dim); actions are bin centres.
* :class:`ValueHead` and :class:`EncodedPolicy` (encoder + optional critic encoder + value head).

Every module casts its inputs to its own parameter dtype (never a hard-coded ``float32``), so a
policy converted with ``.double()`` or ``.to(torch.bfloat16)`` takes the same observations.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from infinirl.models.policies.base import Policy
from infinirl.models.policies.mlp import gaussian_logprob, mlp

__all__ = [
    "BinsHead",
    "ConvEncoder",
    "EncodedPolicy",
    "GaussianHead",
    "ObsEncoder",
    "ValueHead",
    "gaussian_entropy",
    "param_dtype",
    "sinusoidal_embedding",
]

HALF_LOG_2PI_E = 0.5 + 0.5 * math.log(2 * math.pi)
"""Entropy of a standard normal per dim: the Gaussian entropy is this plus ``log_std``."""


def param_dtype(module: nn.Module) -> torch.dtype:
    """The floating dtype of ``module``'s first parameter (inputs are cast to it)."""
    for parameter in module.parameters():
        return parameter.dtype
    return torch.get_default_dtype()


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Elementwise entropy of N(., exp(log_std)^2)."""
    return HALF_LOG_2PI_E + log_std


def sinusoidal_embedding(t: torch.Tensor, dim: int, min_period: float = 4e-3,
                         max_period: float = 4.0) -> torch.Tensor:
    """``t`` ``[N]`` in [0, 1] -> ``[N, dim]`` sin/cos features with geometrically spaced periods
    between ``min_period`` and ``max_period`` (the time embedding pi0 uses for flow matching)."""
    if dim % 2:
        raise ValueError(f"time embedding dim must be even, got {dim}")
    fraction = torch.linspace(0.0, 1.0, dim // 2, dtype=t.dtype, device=t.device)
    period = min_period * (max_period / min_period) ** fraction
    angle = t[:, None] * (2 * math.pi / period)[None]
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=-1)


class ConvEncoder(nn.Module):
    """``[B, H, W, C]`` image -> ``[B, features]``: conv stack (ReLU), then Linear + LayerNorm + tanh.

    uint8 images are divided by 255 inside; floating images are taken to be in ``[0, 1]`` already.
    The defaults (32/64/64 channels, kernels 8/4/3, strides 4/2/1) are the Nature-DQN stack: a
    64x64 image becomes 64x4x4 and an 84x84 one 64x7x7 before the projection, a few MFLOPs per
    image. The LayerNorm + tanh projection is DrQ-v2's, which keeps features bounded for the heads.
    """

    def __init__(self, image_shape: Sequence[int] = (64, 64, 3), channels: Sequence[int] = (32, 64, 64),
                 kernels: Sequence[int] = (8, 4, 3), strides: Sequence[int] = (4, 2, 1), features: int = 256):
        super().__init__()
        if not (len(channels) == len(kernels) == len(strides)):
            raise ValueError("channels, kernels and strides must have the same length")
        self.image_shape = tuple(int(size) for size in image_shape)
        if len(self.image_shape) != 3:
            raise ValueError(f"image_shape is (height, width, channels), got {self.image_shape}")
        height, width, in_channels = self.image_shape
        layers: list[nn.Module] = []
        previous = in_channels
        for out_channels, kernel, stride in zip(channels, kernels, strides):
            conv = nn.Conv2d(previous, out_channels, kernel, stride)
            nn.init.orthogonal_(conv.weight, math.sqrt(2))
            nn.init.zeros_(conv.bias)
            layers += [conv, nn.ReLU()]
            previous = out_channels
        self.convs = nn.Sequential(*layers)
        try:
            with torch.no_grad():
                flat = self.convs(torch.zeros(1, in_channels, height, width)).flatten(1).shape[1]
        except RuntimeError as error:
            raise ValueError(
                f"image {self.image_shape} is too small for kernels {tuple(kernels)} and strides "
                f"{tuple(strides)}; use smaller kernels/strides or fewer layers"
            ) from error
        self.project = nn.Sequential(nn.Linear(flat, features), nn.LayerNorm(features), nn.Tanh())
        self.out_dim = features

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        if tuple(image.shape[1:]) != self.image_shape:
            raise ValueError(
                f"expected images [B, H, W, C] = [B, {', '.join(map(str, self.image_shape))}], "
                f"got {tuple(image.shape)}"
            )
        x = image.to(param_dtype(self))
        if image.dtype == torch.uint8:
            x = x / 255.0
        return self.project(self.convs(x.permute(0, 3, 1, 2)).flatten(1))


class ObsEncoder(nn.Module):
    """Observation dict -> ``[B, out_dim]``: conv features of ``obs[rgb_key]`` (when
    ``image_shape`` is given) concatenated with the raw vector ``obs[vector_key]`` (when
    ``vector_dim > 0``). At least one of the two is required."""

    def __init__(self, image_shape: Sequence[int] | None = None, vector_dim: int = 0,
                 vector_key: str = "proprio", rgb_key: str = "rgb", channels: Sequence[int] = (32, 64, 64),
                 kernels: Sequence[int] = (8, 4, 3), strides: Sequence[int] = (4, 2, 1),
                 image_features: int = 256):
        super().__init__()
        if image_shape is None and vector_dim <= 0:
            raise ValueError(
                "an observation encoder needs an image (image_shape) or a vector (vector_dim > 0)"
            )
        self.rgb_key, self.vector_key, self.vector_dim = rgb_key, vector_key, int(vector_dim)
        self.conv = (ConvEncoder(image_shape, channels, kernels, strides, image_features)
                     if image_shape is not None else None)
        # Follows .double()/.to(dtype) like a parameter: the dtype vectors are cast to (a
        # vector-only encoder has no parameter of its own to ask).
        self.register_buffer("_dtype_probe", torch.zeros(()), persistent=False)
        self.out_dim = (self.conv.out_dim if self.conv is not None else 0) + self.vector_dim

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        parts = []
        if self.conv is not None:
            parts.append(self.conv(obs[self.rgb_key]))
        if self.vector_dim:
            vector = obs[self.vector_key]
            if vector.shape[-1] != self.vector_dim:
                raise ValueError(
                    f"expected obs[{self.vector_key!r}] with {self.vector_dim} features, "
                    f"got {tuple(vector.shape)}"
                )
            parts.append(vector.to(self._dtype_probe.dtype))
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)


class ValueHead(nn.Module):
    """``[B, F]`` features -> ``[B]`` state value (orthogonal MLP, gain 1 on the output)."""

    def __init__(self, in_dim: int, hidden: Sequence[int] = (256,)):
        super().__init__()
        self.net = mlp([in_dim, *hidden, 1], out_gain=1.0)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features).squeeze(-1)


class GaussianHead(nn.Module):
    """``[B, F]`` features -> diagonal Gaussian over ``chunk * action_dim`` action elements.

    ``state_dependent_std=False`` (default): one learned log-std per action element, independent
    of the observation (the cleanRL/PPO default; exploration shrinks only as PPO learns it).
    ``True``: the network also outputs the log-std, squashed into ``[log_std_min, log_std_max]``
    with a tanh (SAC-style), for tasks whose useful noise depends on the state. The mean is not
    squashed (envs clip to their box), as in :class:`MLPGaussianPolicy`.
    """

    def __init__(self, in_dim: int, action_dim: int, chunk: int = 1, hidden: Sequence[int] = (256,),
                 init_log_std: float = 0.0, state_dependent_std: bool = False,
                 log_std_min: float = -5.0, log_std_max: float = 2.0):
        super().__init__()
        self.action_dim, self.chunk = action_dim, chunk
        self.state_dependent_std = state_dependent_std
        self.log_std_min, self.log_std_max = log_std_min, log_std_max
        size = action_dim * chunk
        self.net = mlp([in_dim, *hidden, size * (2 if state_dependent_std else 1)], out_gain=0.01)
        if state_dependent_std:
            # Start at init_log_std: pick the output bias so the squashed value equals it.
            target = (init_log_std - log_std_min) / (log_std_max - log_std_min) * 2 - 1
            with torch.no_grad():
                self.net[-1].bias[size:] = math.atanh(min(max(target, -0.999), 0.999))
            self.log_std = None
        else:
            self.log_std = nn.Parameter(torch.full((size,), float(init_log_std)))

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mean, log_std)``, both ``[B, chunk * action_dim]``."""
        out = self.net(features)
        if not self.state_dependent_std:
            return out, self.log_std.expand_as(out)
        mean, raw = out.chunk(2, dim=-1)
        squashed = (torch.tanh(raw) + 1) / 2
        return mean, self.log_std_min + (self.log_std_max - self.log_std_min) * squashed

    def sample(self, features: torch.Tensor, deterministic: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """``(actions [B, K, A], logprobs [B, K])``."""
        mean, log_std = self(features)
        actions = mean if deterministic else mean + torch.randn_like(mean) * log_std.exp()
        return self._shape(actions), self._per_action(gaussian_logprob(actions, mean, log_std))

    def evaluate(self, features: torch.Tensor, actions: torch.Tensor,
                 with_entropy: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(logprobs [B, K], entropy [B, K] or None)`` of ``actions [B, K, A]`` (taken as data:
        detached, so act's reparameterised samples are not differentiated through)."""
        mean, log_std = self(features)
        logprobs = gaussian_logprob(actions.detach().reshape(mean.shape).to(mean.dtype), mean, log_std)
        entropy = self._per_action(gaussian_entropy(log_std)) if with_entropy else None
        return self._per_action(logprobs), entropy

    def _shape(self, flat: torch.Tensor) -> torch.Tensor:
        return flat.view(flat.shape[0], self.chunk, self.action_dim)

    def _per_action(self, elementwise: torch.Tensor) -> torch.Tensor:
        return self._shape(elementwise).sum(-1)


def _per_dim(value: float | Sequence[float] | np.ndarray, action_dim: int, name: str) -> torch.Tensor:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim == 0:
        array = np.full(action_dim, float(array))
    array = array.reshape(-1)
    if array.shape != (action_dim,):
        raise ValueError(f"{name} must be a number or {action_dim} numbers, got shape {array.shape}")
    return torch.as_tensor(array)


class BinsHead(nn.Module):
    """``[B, F]`` features -> one categorical over ``num_bins`` bins per (chunk step, action dim).

    Dim ``d`` of the box ``[low_d, high_d]`` is cut into ``num_bins`` equal bins; an action is the
    centre of its bin, ``low + (i + 0.5) * (high - low) / num_bins``. The log-prob of an action is
    the sum over dims of the categorical log-probs of its bins, and the entropy is exact (sum of
    the per-dim categorical entropies): the dims are independent given the features, as in
    RT-2/OpenVLA-style discretised heads. Continuous actions map to the bin that contains them
    (clamped to the box), so expert demonstrations can be scored directly.
    """

    def __init__(self, in_dim: int, action_dim: int, chunk: int = 1, num_bins: int = 256,
                 low: float | Sequence[float] = -1.0, high: float | Sequence[float] = 1.0,
                 hidden: Sequence[int] = (256,)):
        super().__init__()
        if num_bins < 2:
            raise ValueError(f"num_bins must be at least 2, got {num_bins}")
        self.action_dim, self.chunk, self.num_bins = action_dim, chunk, num_bins
        low_t, high_t = _per_dim(low, action_dim, "low"), _per_dim(high, action_dim, "high")
        if not bool((high_t > low_t).all()):
            raise ValueError(
                f"every high must exceed its low; got low={low_t.tolist()} high={high_t.tolist()}"
            )
        self.register_buffer("low", low_t.float())
        self.register_buffer("high", high_t.float())
        self.net = mlp([in_dim, *hidden, chunk * action_dim * num_bins], out_gain=0.01)

    @property
    def centres(self) -> torch.Tensor:
        """``[A, num_bins]`` bin centres."""
        steps = torch.arange(self.num_bins, dtype=self.low.dtype, device=self.low.device) + 0.5
        return self.low[:, None] + steps[None] * ((self.high - self.low) / self.num_bins)[:, None]

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Log-probabilities ``[B, K, A, num_bins]``."""
        logits = self.net(features).view(features.shape[0], self.chunk, self.action_dim, self.num_bins)
        return torch.log_softmax(logits, dim=-1)

    def to_index(self, actions: torch.Tensor) -> torch.Tensor:
        """Bin index ``[B, K, A]`` (long) of each action element (clamped into the box)."""
        low, high = self.low.to(torch.float64), self.high.to(torch.float64)
        position = (actions.to(torch.float64) - low) / (high - low) * self.num_bins
        return position.floor().long().clamp(0, self.num_bins - 1)

    def to_action(self, index: torch.Tensor) -> torch.Tensor:
        """Bin centres ``[B, K, A]`` of bin indices ``[B, K, A]``."""
        centres = self.centres.expand(*index.shape[:-1], self.action_dim, self.num_bins)
        return centres.gather(-1, index[..., None]).squeeze(-1)

    def sample(self, features: torch.Tensor, deterministic: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """``(actions [B, K, A] bin centres, logprobs [B, K])``."""
        logp = self(features)
        if deterministic:
            index = logp.argmax(-1)
        else:
            index = torch.multinomial(logp.detach().exp().reshape(-1, self.num_bins).float(), 1)
            index = index.view(logp.shape[:-1])
        logprobs = logp.gather(-1, index[..., None]).squeeze(-1).sum(-1)
        return self.to_action(index).to(logp.dtype), logprobs

    def evaluate(self, features: torch.Tensor, actions: torch.Tensor,
                 with_entropy: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        logp = self(features)
        index = self.to_index(actions.reshape(logp.shape[:-1]))
        logprobs = logp.gather(-1, index[..., None]).squeeze(-1).sum(-1)
        entropy = -(logp.exp() * logp).sum(-1).sum(-1) if with_entropy else None
        return logprobs, entropy


class EncodedPolicy(Policy):
    """A policy whose heads read one feature vector from an :class:`ObsEncoder`.

    The value head reads the *shared* encoder's features by default (``separate_critic=False``):
    one encoder pass serves both heads and the value loss also shapes the features, which often
    speeds up learning from pixels; the price is that value and policy gradients mix in the
    encoder, so the value-loss coefficient matters. ``separate_critic=True`` gives the critic its
    own encoder (PPG's argument: no interference), at twice the encoder compute.
    """

    critic_modules = ("critic", "critic_encoder")

    encoder: ObsEncoder

    def _init_value(self, value_head: bool, separate_critic: bool, value_hidden: Sequence[int],
                    encoder_kwargs: dict) -> None:
        self.has_value_head = value_head
        self.critic_encoder = ObsEncoder(**encoder_kwargs) if value_head and separate_critic else None
        self.critic = ValueHead(self.encoder.out_dim, value_hidden) if value_head else None

    def _values(self, obs, features: torch.Tensor) -> torch.Tensor | None:
        if self.critic is None:
            return None
        if self.critic_encoder is not None:
            features = self.critic_encoder(obs)
        return self.critic(features)

    def value(self, obs) -> torch.Tensor:
        if self.critic is None:
            raise NotImplementedError(f"{type(self).__name__} was built with value_head=False")
        return self._values(obs, self.encoder(obs) if self.critic_encoder is None else None)
