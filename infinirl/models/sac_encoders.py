"""Observation encoders in front of SAC's actor and critics, chosen by name (``network.encoder``).

* ``state``: no encoder; the networks read the ``state`` vector as they always have
  (:mod:`infinirl.models.sac_nets` unchanged, so a state run is bit-identical with or without this
  module).
* ``cnn``: :class:`PixelEncoder`, a small conv stack per camera for uint8 ``HxWx3`` frames
  (``pixels.<camera>``), normalised inside the network (``x / 255 - 0.5``); every camera's
  flattened features are projected to ``feature_dim`` (Linear, LayerNorm, tanh, as in DrQ), then the
  ``state`` vector (proprio and the rest) is concatenated after the encoder.

**Who trains the encoder** (SAC-AE, Yarats et al. 2019; DrQ, Kostrikov et al. 2020): one encoder
module is shared by the actor (:class:`EncodedActor`) and the critics (:class:`EncodedCritic`).
The critic loss trains it (it is among the critic's parameters); the actor reads its features
detached and its optimiser holds only the actor head (:meth:`EncodedActor.head_parameters`), so the
actor loss never moves the encoder. The target critics hold a Polyak-averaged copy of it.
The actor's ``state_dict`` carries the encoder (``encoder.*``), so a weight sync gives a robot's
actor copy everything it needs to act from frames.

**Augmentation** (:func:`random_shift`, DrQ): each frame is shifted by up to ``pad`` pixels in
each direction with edge replication (the same as padding by ``pad`` with the border pixels and
cropping back a random window), one shift per sample and camera, drawn from an explicit generator.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import nn

from infinirl.registry import Registry

__all__ = ["ENCODERS", "EncodedActor", "EncodedCritic", "PixelEncoder", "PIXELS_PREFIX", "random_shift",
           "random_shift_observations"]

PIXELS_PREFIX = "pixels."
"""Observation keys of camera frames: ``pixels.<camera>`` (uint8, ``[B, H, W, 3]``)."""

ENCODERS: Registry = Registry("SAC observation encoder")
"""name -> ``builder(*, obs_dim, cameras, **options)`` returning an encoder module (with ``out_dim``)
or None (the networks read ``state`` directly)."""

_KERNEL = 3


@ENCODERS.register("state")
def state_encoder(*, obs_dim: int, cameras: Mapping[str, tuple[int, int]] | None = None, **options):
    """No encoder: the actor and critics read the ``state`` vector."""
    if options:
        raise ValueError(f"the state encoder takes no options, got {sorted(options)}")
    return None


@ENCODERS.register("cnn")
def cnn_encoder(*, obs_dim: int, cameras: Mapping[str, tuple[int, int]] | None = None, **options):
    """:class:`PixelEncoder` over ``cameras`` (name -> (height, width)) and the ``obs_dim`` state."""
    if not cameras:
        raise ValueError("the cnn encoder needs at least one camera (task.cameras)")
    return PixelEncoder(cameras, obs_dim, **options)


def conv_output_size(size: int, strides: Sequence[int]) -> int:
    """Side of a frame after the unpadded ``3x3`` convolutions with ``strides``."""
    for stride in strides:
        size = (size - _KERNEL) // stride + 1
    return size


class PixelEncoder(nn.Module):
    """``{pixels.<camera>: uint8 [B, H, W, 3], state: [B, S]} -> [B, feature_dim + S]``.

    Args:
        cameras: camera name -> (height, width); each camera has a conv trunk of its own.
        state_dim: size of the ``state`` vector concatenated after the encoder (0: none).
        channels / strides: output channels and stride of each ``3x3`` conv layer (ReLU between).
        feature_dim: size of the projected image features.
    """

    def __init__(self, cameras: Mapping[str, tuple[int, int]], state_dim: int, channels: Sequence[int] = (32, 32, 32),
                 strides: Sequence[int] = (2, 2, 1), feature_dim: int = 64):
        super().__init__()
        if len(channels) != len(strides) or not channels:
            raise ValueError(f"cnn channels {list(channels)} and strides {list(strides)} need one entry per layer")
        self.cameras = {str(name): (int(h), int(w)) for name, (h, w) in cameras.items()}
        self.trunks = nn.ModuleDict()
        flat = 0
        for name, (height, width) in self.cameras.items():
            out_h, out_w = conv_output_size(height, strides), conv_output_size(width, strides)
            if out_h < 1 or out_w < 1:
                raise ValueError(f"camera {name!r} ({height}x{width}) is too small for {len(strides)} conv layers "
                                 f"with strides {list(strides)}")
            layers: list[nn.Module] = []
            size = 3
            for width_out, stride in zip(channels, strides):
                layers += [nn.Conv2d(size, width_out, _KERNEL, stride=stride), nn.ReLU()]
                size = width_out
            self.trunks[name] = nn.Sequential(*layers, nn.Flatten())
            flat += size * out_h * out_w
        self.project = nn.Linear(flat, feature_dim)
        self.norm = nn.LayerNorm(feature_dim)
        self.state_dim = int(state_dim)
        self.out_dim = int(feature_dim) + self.state_dim

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        dtype = self.project.weight.dtype
        features = []
        for name, trunk in self.trunks.items():
            frames = obs[PIXELS_PREFIX + name]
            x = frames.permute(0, 3, 1, 2).to(dtype) / 255.0 - 0.5  # uint8 HWC -> float NCHW in [-0.5, 0.5]
            features.append(trunk(x))
        z = torch.tanh(self.norm(self.project(torch.cat(features, dim=-1))))
        if not self.state_dim:
            return z
        return torch.cat([z, obs["state"].to(dtype)], dim=-1)


class EncodedActor(nn.Module):
    """An encoder, then an actor head (a :class:`~infinirl.models.sac_nets.SquashedGaussianActor` or
    :class:`~infinirl.models.sac_nets.FlowSACActor` built for ``encoder.out_dim`` inputs); the head
    reads the encoder's features detached."""

    def __init__(self, encoder: nn.Module, head: nn.Module):
        super().__init__()
        self.encoder, self.head = encoder, head
        self.action_dim = head.action_dim

    def features(self, obs) -> torch.Tensor:
        return self.encoder(obs).detach()

    @property
    def masks_logprob(self) -> bool:
        return getattr(self.head, "masks_logprob", False)

    def sample(self, obs, generator: torch.Generator | None = None, deterministic: bool = False, **mask):
        """The head's sample of the features; ``mask=`` where the head takes one (``masks_logprob``)."""
        return self.head.sample(self.features(obs), generator, deterministic=deterministic, **mask)

    def logprob_of(self, obs, u: torch.Tensor):
        return self.head.logprob_of(self.features(obs), u)

    def to_env(self, action: torch.Tensor) -> torch.Tensor:
        return self.head.to_env(action)

    def head_parameters(self):
        """What the actor loss trains: the head only (the critic loss trains the encoder)."""
        return self.head.parameters()


class EncodedCritic(nn.Module):
    """An encoder (shared with the actor, trained by the critic loss), then an
    :class:`~infinirl.models.sac_nets.EnsembleQ` head; ``forward`` returns ``[K, B]``."""

    def __init__(self, encoder: nn.Module, head: nn.Module):
        super().__init__()
        self.encoder, self.head = encoder, head
        self.num_critics = head.num_critics

    def forward(self, obs, action: torch.Tensor) -> torch.Tensor:
        return self.head(self.encoder(obs), action)


def random_shift(frames: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``frames`` ``[B, H, W, C]`` each shifted by a random ``(dy, dx)`` in ``[-pad, pad]^2`` with the
    border replicated (pad by ``pad`` with edge pixels, crop a random ``HxW`` window). The shifts are
    drawn on the CPU from ``generator`` (the same draws on any device)."""
    if pad <= 0:
        return frames
    batch, height, width = frames.shape[:3]
    shifts = torch.randint(0, 2 * pad + 1, (batch, 2), generator=generator).to(frames.device) - pad
    rows = (torch.arange(height, device=frames.device)[None] + shifts[:, :1]).clamp_(0, height - 1)
    cols = (torch.arange(width, device=frames.device)[None] + shifts[:, 1:]).clamp_(0, width - 1)
    index = torch.arange(batch, device=frames.device)[:, None, None]
    return frames[index, rows[:, :, None], cols[:, None, :]]


def random_shift_observations(obs: Mapping[str, torch.Tensor], pad: int,
                              generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """``obs`` with every camera's frames shifted by :func:`random_shift` (its own shifts per camera,
    in sorted key order); other fields unchanged."""
    shifted = dict(obs)
    for key in sorted(obs):
        if key.startswith(PIXELS_PREFIX):
            shifted[key] = random_shift(obs[key], pad, generator)
    return shifted
