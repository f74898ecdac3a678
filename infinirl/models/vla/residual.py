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
  trainer's update runs the two MLPs only, never the VLA;
* with ``residual_input_norm``, those inputs are standardised per dimension with the mean and std
  of the first batch the trainer sees (then fixed: buffers, saved and synced with the weights). The
  VLA's pooled features vary mostly between tasks; what tells one layout of a task from another
  (where the button is) is a direction of small variance that a raw MLP is slow to pick up;
* with ``residual_pixels``, ``f`` and the critic each also read the camera frame through a small
  CNN of their own (trained by PPO, the critic's at the value rate): the VLA's pooled features keep
  little of where things are, which a correction of the hand's motion may need. The frame is the
  observation's, so the update runs the CNNs on the batch's frames (still never the VLA);
* with ``held_noise`` (a fraction ``beta`` of the noise's variance), exploration is correlated in
  time, as generalised state-dependent exploration (gSDE, Raffin et al. 2022) is: the sampled
  residual is ``mu + sigma * (sqrt(1 - beta) * xi + sqrt(beta) * z(s) . w)`` with ``xi`` fresh
  every decision, ``z(s)`` the residual network's last hidden layer scaled to unit length and ``w``
  a standard normal matrix per env drawn anew every ``held_noise_every`` decisions (the rollout
  seeds it, :meth:`hold_noise`). The frozen VLA barely corrects the hand's position (it replays a
  motion), so independent noise averages out within a few steps, while a held part keeps pushing one
  way for the whole window: episodes then differ by the centimetres a layout-dependent detour needs,
  not by millimetres. As ``z . w`` is standard normal for a unit ``z``, each residual's density is
  still ``N(mu, sigma^2)``: the log-probs, and so PPO's ratio, are unchanged (the decisions'
  correlation is what they ignore, as gSDE's do);
* with ``residual_readout`` (an observation field the simulator gives in training, e.g. MetaWorld's
  ``state``), ``f`` and the critic also read a linear readout of that field from the features: a
  ridge regression (:class:`~infinirl.models.ridge_readout.RidgeReadout`) refitted after every
  update on all the training batches so far, its prediction standardised per value. The pooled
  features do hold where the object is (a ridge probe reads it off them almost exactly:
  ``scripts/diagnose_vla_episodes.py --probe``), but along directions of small variance that PPO's
  gradient on a raw MLP barely follows; the readout hands the residual a few well-scaled numbers.
  Acting needs the features only, never the field: the deployed policy computes its estimate from
  the camera, instruction and proprio.

PPO's log-probs are per executed action (the chunk's actions are independent given ``s``), the
Gaussian densities of the recorded residual.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence

import torch
from torch import nn

from infinirl.models.policies.base import POLICIES, PolicyEval, PolicyStep
from infinirl.models.policies.heads import gaussian_entropy
from infinirl.models.policies.mlp import gaussian_logprob
from infinirl.models.ridge_readout import RidgeReadout
from infinirl.models.running_stats import RunningMeanStd
from infinirl.models.sac_encoders import PIXELS_PREFIX, PixelEncoder
from infinirl.models.vla.frozen import FrozenVLA, mlp
from infinirl.models.vla.policy import PiZeroFivePolicy, PiZeroPolicy, PiZeroSmolLM2Policy

__all__ = ["PiZeroFiveResidualPolicy", "PiZeroResidualPolicy", "PiZeroSmolLM2ResidualPolicy", "ResidualCorrection"]


_INPUT_CLIP = 10.0  # standardised inputs beyond 10 std are clipped, as the observation normaliser does


def instruction_key(text: str) -> int:
    """A stable nonzero int64 key of an instruction (the same in every process and run)."""
    return int.from_bytes(hashlib.blake2b(str(text).encode(), digest_size=7).digest(), "little") + 1


def _frame_encoder(size: int, width: int) -> PixelEncoder:
    """A small CNN on one camera's uint8 ``size x size`` frames."""
    return PixelEncoder({"frame": (size, size)}, state_dim=0, feature_dim=width)


def _resized(frames: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 ``[B, H, W, 3]`` frames at ``size x size`` (bilinear; unchanged when they are)."""
    if tuple(frames.shape[1:3]) == (size, size):
        return frames
    chw = torch.nn.functional.interpolate(frames.permute(0, 3, 1, 2).float(), size=(size, size), mode="bilinear",
                                          antialias=True, align_corners=False)
    return chw.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1)


class ResidualCorrection(FrozenVLA):
    """Turns a :class:`~infinirl.models.vla.policy.PiZeroPolicy` subclass into its residual form.

    Args (besides the VLA policy's; its flow-SDE options do not apply):
        residual_hidden: the residual policy's and the critic's hidden widths.
        residual_std: ``sigma`` at the start, in the env's action units.
        residual_bound: the largest residual mean per dim (``tanh`` squashed).
        residual_pixels: the residual policy and the critic also read the first camera's frames
            through CNNs of their own (:class:`~infinirl.models.sac_encoders.PixelEncoder`,
            ``pixel_features`` wide, frames resized to ``pixel_size``).
        residual_input_norm: standardise the MLPs' inputs (features and base chunk) with the first
            training batch's statistics (:meth:`fit_input_stats`).
        held_noise: the fraction of the exploration noise's variance held over decisions (0: none).
        held_noise_every: decisions a held draw lasts (within one rollout iteration).
        residual_readout: an observation field (a flat vector seen in training) the residual
            policy and the critic read as a ridge readout of the features; ``residual_readout_dim``
            its size (filled from the env's spec by the embodied runner), ``readout_penalty`` the
            ridge term (:class:`~infinirl.models.ridge_readout.RidgeReadout`); ``readout_groups``
            > 1 fits one readout per instruction (up to that many), keyed by its hash.
        critic_obs: an observation field the critic alone also reads (:class:`FrozenVLA`);
            ``critic_obs_dim`` its size (filled from the env's spec by the embodied runner).
    """

    demo_refusal = "the VLA is frozen and only the residual policy trains, which demonstrations do not label"
    joint_chunk_logprob = False  # one independent Gaussian residual per row: only executed rows count

    def __init__(self, *args, residual_hidden: Sequence[int] = (256, 256), residual_std: float = 0.2,
                 residual_bound: float = 1.0, residual_pixels: bool = False, pixel_features: int = 64,
                 pixel_size: int = 64, residual_input_norm: bool = False, held_noise: float = 0.0,
                 held_noise_every: int = 5, residual_readout: str | None = None,
                 residual_readout_dim: int | None = None, readout_penalty: float = 1e-2, readout_groups: int = 1,
                 critic_obs: str | None = None, critic_obs_dim: int | None = None,
                 value_head: bool = True, **kwargs):
        if residual_std <= 0 or residual_bound <= 0:
            raise ValueError(f"residual_std and residual_bound must be > 0, got {residual_std} and {residual_bound}")
        if not 0.0 <= held_noise <= 1.0 or int(held_noise_every) < 1:
            raise ValueError(f"held_noise must be in [0, 1] and held_noise_every >= 1, got {held_noise} and "
                             f"{held_noise_every}")
        super().__init__(*args, value_head=False, **kwargs)
        features = self._freeze() + self.chunk * self.action_dim
        self.input_rms = RunningMeanStd((features,)) if residual_input_norm else None
        self.readout_obs, self.readout = residual_readout, None
        if residual_readout is not None:
            if int(readout_groups) < 1 or not readout_penalty > 0:
                raise ValueError(f"readout_groups must be >= 1 and readout_penalty > 0, got {readout_groups} and "
                                 f"{readout_penalty}")
            if not residual_readout_dim or residual_readout_dim <= 0:
                raise ValueError(f"residual_readout={residual_readout!r} needs residual_readout_dim, the field's "
                                 "size (the embodied runner fills it from the env's observation spec)")
            self.readout = RidgeReadout(features, int(residual_readout_dim), penalty=readout_penalty,
                                        clip=_INPUT_CLIP, groups=readout_groups)
            features += int(residual_readout_dim)
        self.pixel_key = next(iter(self.cameras)) if residual_pixels else None
        self.residual_encoder = self.value_encoder = None
        if residual_pixels:
            self.pixel_size = int(pixel_size)
            self.residual_encoder = _frame_encoder(self.pixel_size, pixel_features)
            self.value_encoder = _frame_encoder(self.pixel_size, pixel_features) if value_head else None
            self.critic_modules = ("value_net", "value_encoder")
            features += pixel_features
        self.residual_net = mlp(features, residual_hidden, self.chunk * self.action_dim, zero_last=True)
        self.residual_log_std = nn.Parameter(torch.full((self.action_dim,), math.log(residual_std)))
        self.residual_bound = float(residual_bound)
        self.held_noise = float(held_noise)
        self.held_noise_every = int(held_noise_every) if held_noise > 0 else 0
        self._held_seed: int | None = None
        self.has_value_head = value_head
        critic_width = features + self._privileged_width(critic_obs, critic_obs_dim)
        self.value_net = mlp(critic_width, residual_hidden, 1) if value_head else None

    def base(self, obs) -> tuple[torch.Tensor, torch.Tensor]:
        """The VLA's noise-free chunk ``[B, chunk, action_dim]`` and the residual policy's input
        ``[B, features + chunk * action_dim]``."""
        features, x, prefix = self.features(obs)
        config = self.vla.config
        noise = torch.zeros(len(features), config.chunk_size, config.max_action_dim, device=features.device)
        base = self.decode(x, prefix, noise)
        return base, torch.cat([features, base.reshape(len(base), -1)], dim=-1)

    @torch.no_grad()
    def fit_input_stats(self, extras) -> None:
        """With ``residual_input_norm``: the first call sets the inputs' standardisation from
        ``extras['features']`` (a training batch's); later calls keep it. Until then the inputs pass
        unchanged, which the zero-initialised output layer makes harmless: the residual's mean is 0
        either way."""
        if self.input_rms is None or float(self.input_rms.count) >= 1.0:
            return
        if not extras or "features" not in extras:
            raise ValueError("residual_input_norm fits its statistics on extras['features'] from act(), which the "
                             "batch lacks")
        features = torch.as_tensor(extras["features"]).to(self.input_rms.mean.device, torch.float64)
        features = features.reshape(-1, self.input_rms.mean.shape[0])
        self.input_rms.mean.copy_(features.mean(0))
        self.input_rms.var.copy_(features.var(0, unbiased=False))
        self.input_rms.count.fill_(float(len(features)))

    def _normalized(self, inputs: torch.Tensor) -> torch.Tensor:
        if self.input_rms is None or float(self.input_rms.count) < 1.0:
            return inputs
        return self.input_rms.normalize(inputs, _INPUT_CLIP).to(inputs.device)

    def _readout_keys(self, obs, batch: int) -> torch.Tensor | None:
        """With ``readout_groups > 1``: each row's group key, a hash of its instruction."""
        if self.readout is None or self.readout.groups == 1:
            return None
        return torch.tensor([instruction_key(text) for text in self._instructions(obs, batch)], dtype=torch.int64)

    def _recorded_keys(self, extras) -> torch.Tensor | None:
        if self.readout is None or self.readout.groups == 1:
            return None
        if "readout_key" not in extras:
            raise ValueError("readout_groups > 1 reads extras['readout_key'] from act(), which the batch lacks")
        return extras["readout_key"]

    @torch.no_grad()
    def fit_readout(self, obs, extras) -> dict[str, float]:
        """With ``residual_readout``: scores the readout on a training batch it has not seen (R²
        averaged over the field's values that vary; ``train/readout_r2``, absent before the first
        fit), folds the batch in and refits. Called after the update, so a batch's acting and its
        update read the same readout."""
        if self.readout is None:
            return {}
        if not extras or "features" not in extras:
            raise ValueError("residual_readout fits on extras['features'] from act(), which the batch lacks")
        if obs is None or self.readout_obs not in obs:
            raise ValueError(f"residual_readout={self.readout_obs!r}: the training batch's observation lacks that "
                             "field")
        x, y, keys = extras["features"], obs[self.readout_obs], self._recorded_keys(extras)
        score = self.readout.score(x, y, keys)
        self.readout.accumulate(x, y, keys)
        self.readout.refit()
        return {} if math.isnan(score) else {"train/readout_r2": score}

    def _with_pixels(self, inputs: torch.Tensor, obs, encoder: nn.Module | None, keys=None) -> torch.Tensor:
        raw, inputs = inputs, self._normalized(inputs)
        if self.readout is not None:
            inputs = torch.cat([inputs, self.readout(raw, keys)], dim=-1)
        if encoder is None:
            return inputs
        if obs is None or self.pixel_key not in obs:
            raise ValueError(f"residual_pixels reads the observation's {self.pixel_key!r} frames, which it lacks")
        frames = _resized(torch.as_tensor(obs[self.pixel_key]).to(inputs.device), self.pixel_size)
        return torch.cat([inputs, encoder({PIXELS_PREFIX + "frame": frames})], dim=-1)

    def _critic_of(self, inputs: torch.Tensor, obs, keys=None) -> torch.Tensor | None:
        if self.value_net is None:
            return None
        return self._critic(self._with_pixels(inputs, obs, self.value_encoder, keys), obs)

    def residual_distribution(self, inputs: torch.Tensor, obs=None, keys=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``mu`` ``[B, chunk, action_dim]`` and ``log sigma`` (broadcast to it); ``obs`` carries the
        frames with ``residual_pixels``."""
        return self._distribution_and_latent(inputs, obs, keys)[:2]

    def _distribution_and_latent(self, inputs: torch.Tensor, obs,
                                 keys=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``mu``, ``log sigma`` and the residual network's last hidden layer ``[B, hidden]``."""
        latent = self.residual_net[:-1](self._with_pixels(inputs, obs, self.residual_encoder, keys))
        raw = self.residual_net[-1](latent).reshape(-1, self.chunk, self.action_dim)
        mean = self.residual_bound * torch.tanh(raw / self.residual_bound)
        return mean, self.residual_log_std.expand_as(mean), latent

    def hold_noise(self, seed: int) -> None:
        """The next sampled :meth:`act` draws its held matrices ``w`` from ``seed`` (one use);
        without one (e.g. a stochastic evaluation) they are drawn afresh each decision."""
        self._held_seed = int(seed)

    @torch.compiler.disable
    def _held_part(self, latent: torch.Tensor) -> torch.Tensor:
        """``z(s) . w`` per env, chunk position and dim ``[B, chunk, action_dim]``: standard normal."""
        z = latent.detach().float()
        z = z / z.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        shape = (len(z), z.shape[-1], self.chunk * self.action_dim)
        seed, self._held_seed = self._held_seed, None
        generator = None if seed is None else torch.Generator(z.device).manual_seed(seed)
        w = torch.randn(shape, generator=generator, device=z.device)
        return torch.einsum("bl,blo->bo", z, w).reshape(-1, self.chunk, self.action_dim)

    def _exploration(self, mean: torch.Tensor, latent: torch.Tensor) -> torch.Tensor:
        """Standard normal noise per residual, part of it held (``held_noise``)."""
        noise = torch.randn_like(mean)
        if self.held_noise > 0:
            noise = math.sqrt(1.0 - self.held_noise) * noise + math.sqrt(self.held_noise) * self._held_part(latent)
        return noise

    # --- the Policy interface ----------------------------------------------------------------

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        base, inputs = self.base(obs)
        with torch.no_grad():
            keys = self._readout_keys(obs, len(inputs))
            mean, log_std, latent = self._distribution_and_latent(inputs, obs, keys)
            residual = mean if deterministic else mean + log_std.exp() * self._exploration(mean, latent)
            logprobs = gaussian_logprob(residual, mean, log_std).sum(-1)
            values = self._critic_of(inputs, obs, keys)
        extras = {"residual": residual, "features": inputs}
        if keys is not None:
            extras["readout_key"] = keys
        return PolicyStep(actions=base + residual, logprobs=logprobs, values=values, extras=extras)

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        """Log-probs of the recorded residual under the present residual policy: the two MLPs on
        the recorded features (and the CNNs on the frames), no VLA pass."""
        if not extras or "residual" not in extras or "features" not in extras:
            raise ValueError("a residual VLA's evaluate needs extras['residual'] and extras['features'] from act()")
        inputs = extras["features"].detach().float()
        keys = self._recorded_keys(extras)
        mean, log_std = self.residual_distribution(inputs, obs, keys)
        logprobs = gaussian_logprob(extras["residual"].detach().float(), mean, log_std).sum(-1)
        entropy = gaussian_entropy(log_std).sum(-1) if with_entropy else None
        return PolicyEval(logprobs=logprobs, entropy=entropy, values=self._critic_of(inputs, obs, keys))

    def value(self, obs) -> torch.Tensor:
        if self.value_net is None:
            raise NotImplementedError("this residual VLA was built with value_head=False")
        inputs = self.base(obs)[1]
        return self._critic_of(inputs, obs, self._readout_keys(obs, len(inputs)))


@POLICIES.register("pi0_residual")
class PiZeroResidualPolicy(ResidualCorrection, PiZeroPolicy):
    """A π0 checkpoint with a residual policy on its actions (:mod:`infinirl.models.vla.residual`)."""


@POLICIES.register("pi05_residual")
class PiZeroFiveResidualPolicy(ResidualCorrection, PiZeroFivePolicy):
    """A π0.5 checkpoint with a residual policy on its actions."""


@POLICIES.register("pi0_smollm2_residual")
class PiZeroSmolLM2ResidualPolicy(ResidualCorrection, PiZeroSmolLM2Policy):
    """The small ``pi0_smollm2`` VLA with a residual policy on its actions."""
