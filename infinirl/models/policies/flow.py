"""Flow-matching action head with a stochastic (SDE) sampler, so PPO/GRPO can train it.

Registered name: ``flow_matching`` (:class:`FlowMatchingPolicy`).

**Model.** A velocity network ``v(x_tau, tau, c)`` over a whole action chunk ``x`` ``[K, A]``,
conditioned on observation features ``c`` (an :class:`ObsEncoder`: state vector and/or a conv
encoder on ``rgb``). Convention: ``tau`` runs from 0 (noise) to 1 (action), the linear path
``x_tau = tau * a + (1 - tau) * eps`` with ``eps ~ N(0, I)``, and the velocity target is
``a - eps`` (pi0 writes the same path with ``t = 1 - tau`` and ``v_pi0 = -v``).
:meth:`FlowMatchingPolicy.bc_loss` is the conditional flow-matching loss for pretraining on
demonstrations.

**Sampling.** ``num_steps`` = ``N`` uniform steps ``tau_k = k / N`` from ``x_0 ~ N(0, I)``.
Deterministic acting integrates the ODE with Euler steps ``x_{k+1} = x_k + v dtau``. For RL each
step is a Gaussian transition ``x_{k+1} ~ N(mean_k, std_k^2 I)`` (a "two-layer MDP" whose inner
actions are the denoising steps), chosen by ``noise_method``:

* ``"flow_sde"`` (default): the Flow-GRPO SDE (Liu et al. 2025, "Flow-GRPO: Training Flow
  Matching Models via Online RL", eq. 9), as used for pi0 by pi_RL (RLinf, arXiv 2510.25889).
  The ODE is replaced by the reverse-time SDE with the *same marginals*: the drift gets the score
  correction ``(sigma^2 / 2) * grad log p_tau(x)``, and for the linear path the score is
  ``-(x - tau v) / (1 - tau)`` (``x - tau v`` is the predicted noise). Euler-Maruyama gives::

      mean_k = x_k + v dtau - sigma_k^2 dtau / (2 (1 - tau_k)) * (x_k - tau_k v)
      std_k  = sigma_k * sqrt(dtau)

  with Flow-GRPO's schedule ``sigma_k = noise_level * sqrt((1 - tau_k) / tau_k)``, the
  ``tau_0 = 0`` step using ``tau_1`` in the denominator (so the first step's std is
  ``noise_level``). ``noise_level`` (``a`` in the paper; pi_RL uses ~0.5) sets the exploration.
* ``"flow_noise"``: pi_RL's Flow-Noise / ReinFlow (Zhang et al. 2025): the Euler ODE mean and a
  *learned* state-dependent std per element from a noise head on the velocity network's hidden
  features, squashed into ``[min_std, max_std]``. Marginals are not preserved; the noise is
  trained jointly, and deployment uses the ODE.

``sde_steps="all"`` makes every step stochastic; ``"one"`` (pi_RL's mixed ODE-SDE rollout) makes
one uniformly drawn step per sample stochastic and the rest ODE steps, a shorter inner MDP with
lower-variance log-probs.

**Log-prob.** The sum over the stochastic steps of the Gaussian transition log-densities
``log N(x_{k+1}; mean_k, std_k^2 I)``, summed over ``A`` and kept per chunk row, so ``[B, K]``
like every policy (sum over ``K`` for the chunk's joint log-prob). This is the log-density of the
denoising *path* given ``x_0`` (whose own density does not depend on the parameters and cancels
from PPO's ratio). RLinf averages over steps in its joint mode; we sum, which is the path's true
log-probability. ``extras`` carries the path (``chain`` ``[B, N+1, K, A]``, ``sde_mask`` ``[B, N]``)
and :meth:`FlowMatchingPolicy.evaluate` recomputes the same sum differentiably, in one batched
network call over all steps. The entropy is the sum of the transition entropies (the path's
entropy given ``x_0``): a constant for ``flow_sde``, learnable for ``flow_noise``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from infinirl.models.policies.base import POLICIES, PolicyEval, PolicyStep
from infinirl.models.policies.heads import EncodedPolicy, ObsEncoder, gaussian_entropy, sinusoidal_embedding
from infinirl.models.policies.mlp import gaussian_logprob, mlp

__all__ = ["FlowMatchingPolicy", "flow_sde_sigmas", "flow_sde_transition", "flow_timesteps"]

NOISE_METHODS = ("flow_sde", "flow_noise")
SDE_STEPS = ("all", "one")


def flow_timesteps(num_steps: int, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
    """``[N + 1]`` uniform times ``0, 1/N, ..., 1`` (noise -> action)."""
    return torch.linspace(0.0, 1.0, num_steps + 1, dtype=dtype, device=device)


def flow_sde_sigmas(timesteps: torch.Tensor, noise_level: float) -> torch.Tensor:
    """Flow-GRPO's diffusion coefficient at each step start: ``[N]``,
    ``noise_level * sqrt((1 - tau_k) / tau_k)`` with ``tau_1`` standing in for ``tau_0 = 0``."""
    start = timesteps[:-1]
    denominator = torch.where(start == 0, timesteps[1], start)
    return noise_level * torch.sqrt((1 - start) / denominator)


def flow_sde_transition(x: torch.Tensor, v: torch.Tensor, tau: torch.Tensor, dtau: torch.Tensor,
                        sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and std of one Euler-Maruyama step of the marginal-preserving flow SDE
    (``tau``, ``dtau``, ``sigma`` broadcast against ``x``)."""
    score_scale = sigma**2 * dtau / (2 * (1 - tau))
    mean = x + v * dtau - score_scale * (x - tau * v)
    return mean, sigma * torch.sqrt(dtau)


@POLICIES.register("flow_matching")
class FlowMatchingPolicy(EncodedPolicy):
    """Flow-matching policy over action chunks ``[K, A]`` with a flow-SDE sampler for RL.

    ``joint_chunk_logprob``: the chunk is denoised jointly, so at chunk level PPO's ratio is that
    of the whole path, all ``K`` rows, also after an episode ended mid-chunk.

    Args:
        action_dim: action dims ``A``.
        chunk: actions per decision ``K`` (pi0 uses 50; the chunk is denoised jointly).
        obs_dim / obs_key: the low-dimensional observation (``state`` or ``proprio``; 0: none).
        image_shape / rgb_key / channels / kernels / strides / features: the optional conv encoder
            on ``obs[rgb_key]`` (see :class:`~infinirl.models.policies.heads.ConvEncoder`).
        hidden: hidden sizes of the velocity MLP (input: flattened chunk, time embedding, features).
        time_dim: size of the sinusoidal time embedding.
        num_steps: denoising steps ``N`` (pi0: 10).
        noise_method: ``"flow_sde"`` or ``"flow_noise"`` (module docstring).
        noise_level: Flow-SDE's ``a``; an attribute, so it can be annealed (it changes log-probs, so
            change it between PPO iterations, not between ``act`` and ``evaluate``).
        sde_steps: ``"all"`` or ``"one"`` stochastic denoising step(s) per sample.
        min_std / max_std: the learned std's range for ``flow_noise``.
        value_head / separate_critic / value_hidden: critic on the observation features.
    """

    joint_chunk_logprob = True

    def __init__(self, action_dim: int, chunk: int = 1, obs_dim: int = 0, obs_key: str = "state",
                 image_shape: Sequence[int] | None = None, rgb_key: str = "rgb",
                 channels: Sequence[int] = (32, 64, 64), kernels: Sequence[int] = (8, 4, 3),
                 strides: Sequence[int] = (4, 2, 1), features: int = 256, hidden: Sequence[int] = (256, 256),
                 time_dim: int = 32, num_steps: int = 10, noise_method: str = "flow_sde",
                 noise_level: float = 0.5, sde_steps: str = "all", min_std: float = 0.05,
                 max_std: float = 0.5, value_head: bool = True, separate_critic: bool = False,
                 value_hidden: Sequence[int] = (256,)):
        super().__init__()
        if noise_method not in NOISE_METHODS:
            raise ValueError(f"noise_method must be one of {NOISE_METHODS}, got {noise_method!r}")
        if sde_steps not in SDE_STEPS:
            raise ValueError(f"sde_steps must be one of {SDE_STEPS}, got {sde_steps!r}")
        if num_steps < 1:
            raise ValueError(f"num_steps must be at least 1, got {num_steps}")
        if noise_method == "flow_sde" and noise_level <= 0:
            raise ValueError("flow_sde needs noise_level > 0 (its log-probs are Gaussian densities)")
        if noise_method == "flow_noise" and not 0 < min_std < max_std:
            raise ValueError(f"flow_noise needs 0 < min_std < max_std, got {min_std}, {max_std}")
        self.action_dim, self.chunk, self.num_steps = action_dim, chunk, num_steps
        self.noise_method, self.noise_level, self.sde_steps = noise_method, float(noise_level), sde_steps
        self.min_std, self.max_std, self.time_dim = min_std, max_std, time_dim
        encoder_kwargs = dict(image_shape=image_shape, vector_dim=obs_dim, vector_key=obs_key,
                              rgb_key=rgb_key, channels=channels, kernels=kernels, strides=strides,
                              image_features=features)
        self.encoder = ObsEncoder(**encoder_kwargs)
        size = chunk * action_dim
        self.trunk = nn.Sequential(
            mlp([size + time_dim + self.encoder.out_dim, *hidden], activation=nn.SiLU, out_gain=math.sqrt(2)),
            nn.SiLU(),
        )
        self.velocity_out = nn.Linear(hidden[-1], size)
        self.noise_out = nn.Linear(hidden[-1], size) if noise_method == "flow_noise" else None
        self._init_value(value_head, separate_critic, value_hidden, encoder_kwargs)

    # --- the network ---------------------------------------------------------------------------

    def velocity(self, x: torch.Tensor, tau: torch.Tensor,
                 features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``v(x, tau, c)`` ``[M, K, A]`` for chunks ``x`` ``[M, K, A]``, times ``tau`` ``[M]`` and
        features ``[M, F]``; plus the learned std ``[M, K, A]`` for ``flow_noise`` (else None)."""
        batch = x.shape[0]
        inputs = torch.cat([x.reshape(batch, -1), sinusoidal_embedding(tau, self.time_dim), features], dim=-1)
        hidden = self.trunk(inputs)
        v = self.velocity_out(hidden).view_as(x)
        if self.noise_out is None:
            return v, None
        std = self.min_std + (self.max_std - self.min_std) * torch.sigmoid(self.noise_out(hidden))
        return v, std.view_as(x)

    def transition(self, x: torch.Tensor, step: torch.Tensor,
                   features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Denoising step ``step`` (``[M]`` long) from ``x`` ``[M, K, A]``: the stochastic
        transition's ``(mean, std)`` and the deterministic ODE step, each ``[M, K, A]``."""
        timesteps = flow_timesteps(self.num_steps, x.dtype, x.device)
        tau = timesteps[step]
        dtau = (timesteps[step + 1] - tau)[:, None, None]
        v, learned_std = self.velocity(x, tau, features)
        ode = x + v * dtau
        if self.noise_method == "flow_noise":
            return ode, learned_std, ode
        sigma = flow_sde_sigmas(timesteps, self.noise_level)[step][:, None, None]
        mean, std = flow_sde_transition(x, v, tau[:, None, None], dtau, sigma)
        return mean, std.expand_as(mean), ode

    # --- the Policy interface ------------------------------------------------------------------

    def _sde_mask(self, batch: int, deterministic: bool, device) -> torch.Tensor:
        if deterministic or self.sde_steps == "all":
            return torch.ones(batch, self.num_steps, dtype=torch.bool, device=device)
        chosen = torch.randint(self.num_steps, (batch,), device=device)
        return torch.nn.functional.one_hot(chosen, self.num_steps).bool()

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        """Sample a chunk by ``num_steps`` denoising steps (ODE steps when ``deterministic``).

        With ``deterministic=True`` the log-probs are those of the ODE path under the stochastic
        transitions (what :meth:`evaluate` returns for it), a diagnostic rather than a sample's.
        """
        features = self.encoder(obs)
        batch = features.shape[0]
        x = torch.randn(batch, self.chunk, self.action_dim, dtype=features.dtype, device=features.device)
        mask = self._sde_mask(batch, deterministic, features.device)
        chain, logprobs = [x], torch.zeros(batch, self.chunk, dtype=features.dtype, device=features.device)
        for k in range(self.num_steps):
            step = torch.full((batch,), k, dtype=torch.long, device=features.device)
            mean, std, ode = self.transition(x, step, features)
            stochastic = mask[:, k, None, None]
            if deterministic:
                x = ode
            else:
                x = torch.where(stochastic, mean + std * torch.randn_like(mean), ode)
            step_logp = gaussian_logprob(x, mean, std.log()).sum(-1)
            logprobs = logprobs + torch.where(mask[:, k, None], step_logp, torch.zeros_like(step_logp))
            chain.append(x)
        extras = {"chain": torch.stack(chain, dim=1).detach(), "sde_mask": mask}
        return PolicyStep(actions=x, logprobs=logprobs, values=self._values(obs, features), extras=extras)

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        """Differentiable log-probs of the recorded denoising paths (``extras`` from :meth:`act`).

        The path's last state is replaced by ``actions``, so the log-prob is of the actions given.
        """
        if not extras or "chain" not in extras:
            raise ValueError("flow_matching.evaluate needs extras['chain'] (and 'sde_mask') from act()")
        features = self.encoder(obs)
        chain = extras["chain"].detach().to(features.dtype)
        batch, steps_plus_one = chain.shape[:2]
        if steps_plus_one != self.num_steps + 1:
            raise ValueError(
                f"extras['chain'] has {steps_plus_one - 1} denoising steps, the policy {self.num_steps}"
            )
        mask = extras.get("sde_mask")
        if mask is None:
            mask = torch.ones(batch, self.num_steps, dtype=torch.bool, device=chain.device)
        last = actions.detach().to(chain.dtype).view(batch, 1, self.chunk, self.action_dim)
        chain = torch.cat([chain[:, :-1], last], dim=1)
        steps = self.num_steps
        step = torch.arange(steps, device=chain.device).repeat(batch)
        mean, std, _ = self.transition(
            chain[:, :-1].reshape(batch * steps, self.chunk, self.action_dim),
            step,
            features.repeat_interleave(steps, dim=0),
        )
        log_std = std.log()
        logp = gaussian_logprob(chain[:, 1:].reshape_as(mean), mean, log_std)
        logp = logp.sum(-1).view(batch, steps, self.chunk)
        keep = mask.bool()[:, :, None]
        logprobs = torch.where(keep, logp, torch.zeros_like(logp)).sum(1)
        entropy = None
        if with_entropy:
            ent = gaussian_entropy(log_std).sum(-1).view(batch, steps, self.chunk)
            entropy = torch.where(keep, ent, torch.zeros_like(ent)).sum(1)
        return PolicyEval(logprobs=logprobs, entropy=entropy, values=self._values(obs, features))

    def bc_loss(self, obs, actions: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Conditional flow-matching loss on demonstrations ``actions`` ``[B, K, A]``:
        ``E ||v(tau a + (1 - tau) eps, tau, c) - (a - eps)||^2`` with ``tau ~ U(0, 1)``, averaged
        over the chunk's elements, then over samples (``mask`` ``[B]`` drops unlabelled ones)."""
        features = self.encoder(obs)
        target_actions = actions.to(features.dtype).view(features.shape[0], self.chunk, self.action_dim)
        noise = torch.randn_like(target_actions)
        tau = torch.rand(features.shape[0], dtype=features.dtype, device=features.device)
        x = tau[:, None, None] * target_actions + (1 - tau[:, None, None]) * noise
        v, _ = self.velocity(x, tau, features)
        per_sample = ((v - (target_actions - noise)) ** 2).flatten(1).mean(-1)
        if mask is None:
            return per_sample.mean()
        weight = mask.to(per_sample.dtype)
        return (per_sample * weight).sum() / weight.sum().clamp_min(1.0)
