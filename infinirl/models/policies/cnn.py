"""Pixel policies: a small conv encoder on ``rgb`` (optionally with ``proprio``) and one action head.

Registered names:

* ``cnn_gaussian`` (:class:`CNNGaussianPolicy`): diagonal Gaussian head, state-independent
  log-std by default (``state_dependent_std=True`` for a learned, squashed one).
* ``cnn_bins`` (:class:`CNNBinsPolicy`): each action dim discretised into ``num_bins`` bins over
  the action box ``[low, high]``; actions are bin centres (always inside the box).

Both emit chunks of ``chunk`` actions (``actions [B, K, A]``, ``logprobs``/``entropy [B, K]``) and
carry a value head on the shared encoder features unless ``separate_critic=True`` (see
:class:`~infinirl.models.policies.heads.EncodedPolicy` for the trade-off). ``extras`` are empty:
the actions alone determine their log-probs.
"""

from __future__ import annotations

from collections.abc import Sequence

from infinirl.models.policies.base import POLICIES, PolicyEval, PolicyStep
from infinirl.models.policies.heads import BinsHead, EncodedPolicy, GaussianHead, ObsEncoder

__all__ = ["CNNBinsPolicy", "CNNGaussianPolicy"]


class _CNNPolicy(EncodedPolicy):
    """Encoder + ``self.head`` (a :class:`GaussianHead` or :class:`BinsHead`) + optional value."""

    head: GaussianHead | BinsHead

    def _init_encoder(self, action_dim: int, chunk: int, image_shape, proprio_dim: int, proprio_key: str,
                      rgb_key: str, channels, kernels, strides, features: int) -> dict:
        self.action_dim, self.chunk = action_dim, chunk
        encoder_kwargs = dict(image_shape=image_shape, vector_dim=proprio_dim, vector_key=proprio_key,
                              rgb_key=rgb_key, channels=channels, kernels=kernels, strides=strides,
                              image_features=features)
        self.encoder = ObsEncoder(**encoder_kwargs)
        return encoder_kwargs

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        features = self.encoder(obs)
        actions, logprobs = self.head.sample(features, deterministic)
        return PolicyStep(actions=actions, logprobs=logprobs, values=self._values(obs, features))

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        features = self.encoder(obs)
        logprobs, entropy = self.head.evaluate(features, actions, with_entropy)
        return PolicyEval(logprobs=logprobs, entropy=entropy, values=self._values(obs, features))


@POLICIES.register("cnn_gaussian")
class CNNGaussianPolicy(_CNNPolicy):
    """``rgb`` (+ ``proprio``) -> diagonal Gaussian over a chunk of ``chunk`` x ``action_dim`` actions.

    Args:
        action_dim: action dims ``A``.
        chunk: actions per decision ``K``.
        image_shape: ``(H, W, C)`` of ``obs[rgb_key]`` (uint8, or float in [0, 1]).
        proprio_dim: length of ``obs[proprio_key]`` concatenated to the image features (0: none).
        proprio_key: ``"proprio"`` or ``"state"``.
        channels / kernels / strides: the conv stack (default Nature-DQN; fits 64x64 and 84x84).
        features: image feature size after the conv stack's projection.
        hidden: hidden sizes of the action head's MLP.
        init_log_std: initial log-std of every action element.
        state_dependent_std: log-std from the network (tanh-squashed into
            ``[log_std_min, log_std_max]``) instead of a free per-element parameter.
        value_head / separate_critic / value_hidden: critic on the shared (or its own) encoder.
    """

    def __init__(self, action_dim: int, chunk: int = 1, image_shape: Sequence[int] = (64, 64, 3),
                 proprio_dim: int = 0, proprio_key: str = "proprio", rgb_key: str = "rgb",
                 channels: Sequence[int] = (32, 64, 64), kernels: Sequence[int] = (8, 4, 3),
                 strides: Sequence[int] = (4, 2, 1), features: int = 256, hidden: Sequence[int] = (256,),
                 init_log_std: float = 0.0, state_dependent_std: bool = False, log_std_min: float = -5.0,
                 log_std_max: float = 2.0, value_head: bool = True, separate_critic: bool = False,
                 value_hidden: Sequence[int] = (256,)):
        super().__init__()
        encoder_kwargs = self._init_encoder(action_dim, chunk, image_shape, proprio_dim, proprio_key,
                                            rgb_key, channels, kernels, strides, features)
        self.head = GaussianHead(self.encoder.out_dim, action_dim, chunk, hidden, init_log_std,
                                 state_dependent_std, log_std_min, log_std_max)
        self._init_value(value_head, separate_critic, value_hidden, encoder_kwargs)


@POLICIES.register("cnn_bins")
class CNNBinsPolicy(_CNNPolicy):
    """``rgb`` (+ ``proprio``) -> per-dim categorical over ``num_bins`` bins of the box ``[low, high]``.

    Same arguments as :class:`CNNGaussianPolicy` for the encoder and critic, plus:

    Args:
        num_bins: bins per action dim (256 as in RT-2/OpenVLA; fewer learn faster from scratch).
        low / high: the action box, a number or one per dim (``ActionSpace.low``/``high`` fit).
    """

    def __init__(self, action_dim: int, chunk: int = 1, image_shape: Sequence[int] = (64, 64, 3),
                 proprio_dim: int = 0, proprio_key: str = "proprio", rgb_key: str = "rgb",
                 channels: Sequence[int] = (32, 64, 64), kernels: Sequence[int] = (8, 4, 3),
                 strides: Sequence[int] = (4, 2, 1), features: int = 256, hidden: Sequence[int] = (256,),
                 num_bins: int = 256, low: float | Sequence[float] = -1.0,
                 high: float | Sequence[float] = 1.0, value_head: bool = True, separate_critic: bool = False,
                 value_hidden: Sequence[int] = (256,)):
        super().__init__()
        encoder_kwargs = self._init_encoder(action_dim, chunk, image_shape, proprio_dim, proprio_key,
                                            rgb_key, channels, kernels, strides, features)
        self.head = BinsHead(self.encoder.out_dim, action_dim, chunk, num_bins, low, high, hidden)
        self._init_value(value_head, separate_critic, value_hidden, encoder_kwargs)
