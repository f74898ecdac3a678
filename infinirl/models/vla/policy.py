"""π0 / π0.5 as a :class:`~infinirl.models.policies.base.Policy`: flow-SDE log-probs for PPO/GRPO
(or pi_RL's Flow-Noise, ``likelihood="flow_noise"``, or Flow Policy Optimization's
flow-matching-loss scores, ``likelihood="fpo"``).

Registered names: ``pi0``, ``pi05`` and ``pi0_smollm2`` (:class:`PiZeroPolicy`; the checkpoint
folder must be of that family). The denoising loop is the flow head's (:mod:`infinirl.models.policies.flow`): ``N``
steps ``tau_k = k / N`` from ``x_0 ~ N(0, I)``, each a Gaussian transition from
:func:`~infinirl.models.policies.flow.flow_sde_transition` (marginal-preserving flow SDE,
Flow-GRPO's ``sigma_k``), with π0's network as the velocity: π0 time ``t = 1 - tau`` and velocity
``v = -v_pi0``. Deterministic acting is π0's own Euler sampler, step for step.

Flow-Noise (pi_RL's second variant, ReinFlow's noise) keeps each step's mean at the Euler step and
learns its std: a linear ``std_net`` on the action expert's output at the action tokens (what
``action_out_proj`` reads), squashed into ``[min_std, max_std]`` per element and starting at the
middle of that range (zero weights). It trains with the policy (``fresh_modules``: under LoRA it
trains in full), its entropy is learnable, and deployment (deterministic acting) is the ODE.

The chain lives in the model's space (normalised, padded ``[chunk_size, max_action_dim]``); the
env receives the first ``chunk`` rows and ``action_dim`` dims, unnormalised. Log-probs sum the
transition densities of exactly those coordinates (the padding and the rows past ``chunk`` are
sampled but not credited, as in pi_RL): ``[B, chunk]``, one per action sent to the env. At chunk
level PPO sums all ``chunk`` rows (``joint_chunk_logprob``), also those an episode's end left
unexecuted: they were denoised with the rest.
:meth:`PiZeroPolicy.evaluate` recomputes them from the recorded chain (``extras["chain"]``,
``extras["sde_mask"]``), with gradients through the action expert and the VLM prefix.

Observations: the env's dict (``rgb`` uint8 ``[B, H, W, 3]``, ``state``, ``instruction``: list of
str) is renamed to the checkpoint's keys by ``cameras`` (env key -> checkpoint camera key),
``state_key`` and ``instruction_key``. An optional critic (``value_head``) reads the mean of the
VLM's prefix hidden states (``critic_input="prefix"``, π0.5's and RLinf's ``value_after_vlm``), or
of the action expert's outputs at the executed action tokens (``"expert"``, pi_RL's π0 critic: π0's
VLM never sees the state, its expert does), from one expert pass at time 1 with the noise at its
mean (0), so the value is a function of the observation alone.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from infinirl.engines.cpu_dtype import resolve_weights_dtype
from infinirl.models.policies.base import POLICIES, Policy, PolicyEval, PolicyStep
from infinirl.models.policies.flow import flow_sde_sigmas, flow_sde_transition, flow_timesteps
from infinirl.models.policies.heads import gaussian_entropy
from infinirl.models.policies.mlp import gaussian_logprob
from infinirl.models.vla.config import VLAArchitecture
from infinirl.models.vla.processor import STATE, TASK, VLAInputs

if TYPE_CHECKING:
    from infinirl.models.vla.model import PrefixCache
    from infinirl.models.vla.vla import VLA

__all__ = ["PiZeroFivePolicy", "PiZeroPolicy", "PiZeroSmolLM2Policy"]

SDE_STEPS = ("all", "one")
LIKELIHOODS = ("flow_sde", "flow_noise", "fpo")
CRITIC_INPUTS = ("prefix", "expert")
FPO_KEYS = ("fpo_action", "fpo_noise", "fpo_time")


def pooled_prefix(hidden: torch.Tensor, pad_mask: torch.Tensor) -> torch.Tensor:
    """The mean of the prefix's hidden states ``[B, L, W]`` over its real tokens: ``[B, W]`` float32."""
    weight = pad_mask.to(hidden.dtype)[..., None]
    return ((hidden * weight).sum(1) / weight.sum(1).clamp_min(1.0)).float()


@POLICIES.register("pi0")
class PiZeroPolicy(Policy):
    """A LeRobot π0/π0.5 checkpoint acting in an env with flow-SDE exploration.

    Args:
        checkpoint: the LeRobot checkpoint folder (:func:`~infinirl.models.vla.load_vla`), or a
            loaded :class:`~infinirl.models.vla.VLA` of the policy's family (shared, not copied).
        action_dim / chunk: the env's action dims and actions per decision (at most the
            checkpoint's ``action_dim`` / ``chunk_size``).
        tokenizer: the tokenizer's local folder (PaliGemma's), unless the checkpoint has ``tokenizer/``.
        architecture: an ``architecture.json`` path for checkpoints of non-published sizes.
        cameras: env observation key -> checkpoint camera key (default: ``rgb`` -> the first camera).
        state_key / instruction_key: the env's state and instruction fields.
        instruction: the instruction when an observation has no ``instruction_key`` (the embodied
            runner hands policies only the array fields; one task per env makes it fixed).
        num_steps: denoising steps (default: the checkpoint's ``num_inference_steps``).
        noise_level: Flow-SDE's ``a``; sde_steps: ``"all"`` or ``"one"`` stochastic step(s).
        value_head: add a critic (on ``critic_input``); value_hidden: its hidden width.
        critic_input: what the critic reads, ``"prefix"`` (the VLM's) or ``"expert"`` (the action
            expert's output, one more expert pass per decision).
        detach_critic: the critic reads its input without back-propagating into the VLA, so the
            value loss trains the value head only and the VLA's weights move for the policy alone
            (RLinf's ``detach_critic_input`` for π0).
        likelihood: ``"flow_sde"`` (explore with noise along the denoising path, whose Gaussian
            log-probs PPO ratios use), ``"flow_noise"`` (the same path with Euler means and
            learned stds) or ``"fpo"`` (Flow Policy Optimization: act with the policy's own ODE
            sampler, so the policy trained is the one evaluated, and score an action chunk by minus
            its flow-matching loss at ``fpo_samples`` recorded (time, noise) draws; PPO's ratio
            ``exp(L_old - L_new)`` then needs no density).
        min_std / max_std: the range of ``flow_noise``'s learned std (model space: normalised actions).
    """

    critic_modules = ("value_net",)
    demo_refusal = None
    normalizes_own_inputs = True  # the state, with the checkpoint's statistics (processor)
    joint_chunk_logprob = True  # the chunk is denoised (or, for FPO, scored) as a whole

    family: str | None = "pi0"

    def __init__(self, checkpoint: str | VLA, action_dim: int, chunk: int = 1, tokenizer: str | None = None,
                 architecture: str | None = None, cameras: Mapping[str, str] | None = None,
                 state_key: str = "state", instruction_key: str = "instruction", num_steps: int | None = None,
                 noise_level: float = 0.5, sde_steps: str = "all", value_head: bool = True, value_hidden: int = 256,
                 dtype: str = "float32", instruction: str | None = None, detach_critic: bool = False,
                 likelihood: str = "flow_sde", fpo_samples: int = 8, min_std: float = 0.08,
                 max_std: float = 0.16, critic_input: str = "prefix"):
        # Imported here, not at the top: the policy registry imports this module in every process
        # that builds any policy, and transformers' model classes take seconds to import.
        from infinirl.models.vla.vla import VLA, load_vla

        super().__init__()
        if sde_steps not in SDE_STEPS:
            raise ValueError(f"sde_steps must be one of {SDE_STEPS}, got {sde_steps!r}")
        if likelihood not in LIKELIHOODS:
            raise ValueError(f"likelihood must be one of {LIKELIHOODS}, got {likelihood!r}")
        if critic_input not in CRITIC_INPUTS:
            raise ValueError(f"critic_input must be one of {CRITIC_INPUTS}, got {critic_input!r}")
        if fpo_samples < 1:
            raise ValueError(f"fpo_samples must be at least 1, got {fpo_samples}")
        if noise_level <= 0:
            raise ValueError("flow_sde needs noise_level > 0 (its log-probs are Gaussian densities)")
        if likelihood == "flow_noise" and not 0 < min_std < max_std:
            raise ValueError(f"flow_noise needs 0 < min_std < max_std, got min_std={min_std}, max_std={max_std}")
        if isinstance(checkpoint, VLA):
            if checkpoint.config.family != self.family:
                raise ValueError(f"the VLA given is a '{checkpoint.config.family}' model, not '{self.family}'")
            self.vla = checkpoint
        else:
            arch = VLAArchitecture.from_json(architecture) if architecture else None
            self.vla = load_vla(Path(checkpoint), family=self.family, architecture=arch, tokenizer=tokenizer,
                                dtype=resolve_weights_dtype(dtype))
        config = self.vla.config
        if action_dim > config.action_dim or chunk > config.chunk_size:
            raise ValueError(f"the env wants chunks of {chunk} x {action_dim}, the checkpoint gives "
                             f"{config.chunk_size} x {config.action_dim} (chunk_size x action dims)")
        self.action_dim, self.chunk = action_dim, chunk
        self.num_steps = num_steps or config.num_inference_steps
        self.noise_level, self.sde_steps = float(noise_level), sde_steps
        self.likelihood, self.fpo_samples = likelihood, int(fpo_samples)
        self.cameras = dict(cameras or {"rgb": config.camera_keys[0]})
        unknown = sorted(set(self.cameras.values()) - set(config.camera_keys))
        if unknown:
            raise ValueError(f"cameras maps to {unknown}, which the checkpoint does not have: "
                             f"{list(config.camera_keys)}")
        self.state_key, self.instruction_key, self.instruction = state_key, instruction_key, instruction
        self.has_value_head, self.detach_critic, self.critic_input = value_head, detach_critic, critic_input
        width = config.architecture.vlm.width if critic_input == "prefix" else config.architecture.expert.width
        self.value_net = (nn.Sequential(nn.Linear(width, value_hidden), nn.SiLU(), nn.Linear(value_hidden, 1))
                          if value_head else None)
        self.min_std, self.max_std = float(min_std), float(max_std)
        self.std_net = None
        if likelihood == "flow_noise":
            self.std_net = nn.Linear(config.architecture.expert.width, config.max_action_dim)
            nn.init.zeros_(self.std_net.weight)
            nn.init.zeros_(self.std_net.bias)
            self.fresh_modules = ("std_net",)

    # --- observations ------------------------------------------------------------------------

    def inputs(self, obs: Mapping[str, Any]) -> VLAInputs:
        observation = {camera: obs[key] for key, camera in self.cameras.items()}
        observation[STATE] = obs[self.state_key]
        observation[TASK] = self._instructions(obs, len(observation[STATE]))
        return self.vla.inputs(observation)

    def _instructions(self, obs: Mapping[str, Any], batch: int) -> list[str]:
        if self.instruction_key in obs:
            instructions = obs[self.instruction_key]
            return [instructions] if isinstance(instructions, str) else list(instructions)
        if self.instruction is None:
            raise ValueError(f"the observation has no {self.instruction_key!r} (keys: {sorted(obs)}): give the policy "
                             "instruction=... for envs whose observations carry none")
        return [self.instruction] * batch

    def _prefix(self, x: VLAInputs) -> PrefixCache:
        return self.vla.model.encode_prefix(x.images, x.image_masks, x.tokens, x.token_mask)

    def _values(self, prefix: PrefixCache, state: torch.Tensor | None) -> torch.Tensor | None:
        if self.value_net is None:
            return None
        if self.critic_input == "prefix":
            hidden = prefix.hidden.detach() if self.detach_critic else prefix.hidden
            return self.value_net(pooled_prefix(hidden, prefix.pad_mask)).squeeze(-1)
        config = self.vla.config
        batch = prefix.pad_mask.shape[0]
        device = prefix.pad_mask.device
        # The noise's mean at pi0 time 1 (pure noise): a pass that depends on the observation only, so V(s).
        x = torch.zeros(batch, config.chunk_size, config.max_action_dim, device=device)
        _, hidden = self.vla.model.velocity(prefix, state, x, torch.ones(batch, device=device), return_hidden=True)
        hidden = hidden[:, :self.chunk].float().mean(1)
        return self.value_net(hidden.detach() if self.detach_critic else hidden).squeeze(-1)

    # --- denoising ---------------------------------------------------------------------------

    def transition(self, prefix: PrefixCache, state: torch.Tensor | None, x: torch.Tensor,
                   k: int | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Step ``k`` from ``x`` (model space): the SDE transition's ``(mean, std)`` and the ODE step.
        ``k`` is one step for the whole batch or a ``[B]`` tensor, a step per row."""
        timesteps = flow_timesteps(self.num_steps, torch.float32, x.device)
        sigmas = flow_sde_sigmas(timesteps, self.noise_level)
        if isinstance(k, torch.Tensor):
            def per_row(values: torch.Tensor) -> torch.Tensor:
                return values[..., None, None]
            k = k.to(x.device)
        else:
            def per_row(values: torch.Tensor) -> torch.Tensor:
                return values
        tau, dtau = timesteps[k], timesteps[k + 1] - timesteps[k]
        time = torch.ones(x.shape[0], device=x.device) - tau
        if self.std_net is not None:
            v_pi0, hidden = self.vla.model.velocity(prefix, state, x, time, return_hidden=True)
            ode = x - v_pi0.float() * per_row(dtau)
            return ode, self.learned_std(hidden), ode
        v = -self.vla.model.velocity(prefix, state, x, time).float()
        mean, std = flow_sde_transition(x, v, per_row(tau), per_row(dtau), per_row(sigmas[k]))
        return mean, std.expand_as(mean), x + v * per_row(dtau)

    def learned_std(self, hidden: torch.Tensor) -> torch.Tensor:
        """Flow-Noise's std ``[B, chunk_size, max_action_dim]`` from the expert's action-token outputs."""
        squashed = torch.sigmoid(self.std_net(hidden.float()))
        return self.min_std + (self.max_std - self.min_std) * squashed

    def _credited(self, values: torch.Tensor) -> torch.Tensor:
        """``[B, chunk_size, max_action_dim]`` -> the executed coordinates summed over dims ``[B, chunk]``."""
        return values[:, :self.chunk, :self.action_dim].sum(-1)

    def sde_mask(self, batch: int, deterministic: bool, device) -> torch.Tensor:
        if deterministic or self.sde_steps == "all":
            return torch.ones(batch, self.num_steps, dtype=torch.bool, device=device)
        chosen = torch.randint(self.num_steps, (batch,), device=device)
        return torch.nn.functional.one_hot(chosen, self.num_steps).bool()

    @torch.no_grad()
    def denoise(self, x: VLAInputs, noise: torch.Tensor, deterministic: bool = False,
                mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, PrefixCache]:
        """The chain ``[B, N + 1, chunk_size, max_action_dim]`` from ``noise``, its log-probs
        ``[B, chunk]``, the SDE mask ``[B, N]`` and the prefix (ODE steps when ``deterministic``)."""
        prefix = self._prefix(x)
        batch = noise.shape[0]
        mask = self.sde_mask(batch, deterministic, noise.device) if mask is None else mask
        chain, logprobs = [noise.float()], torch.zeros(batch, self.chunk, device=noise.device)
        current = chain[0]
        for k in range(self.num_steps):
            mean, std, ode = self.transition(prefix, x.state, current, k)
            stochastic = mask[:, k, None, None]
            sampled = ode if deterministic else mean + std * torch.randn_like(mean)
            current = torch.where(stochastic, sampled, ode)
            step = self._credited(gaussian_logprob(current, mean, std.log()))
            logprobs = logprobs + torch.where(mask[:, k, None], step, torch.zeros_like(step))
            chain.append(current)
        return torch.stack(chain, dim=1), logprobs, mask, prefix

    # --- the Policy interface ----------------------------------------------------------------

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        x = self.inputs(obs)
        config = self.vla.config
        device = x.tokens.device
        noise = torch.randn(x.tokens.shape[0], config.chunk_size, config.max_action_dim, device=device)
        fpo = self.likelihood == "fpo"
        chain, logprobs, mask, prefix = self.denoise(x, noise, deterministic or fpo)
        actions = self.vla.processor.actions_out(chain[:, -1])[:, :self.chunk, :self.action_dim]
        with torch.no_grad():
            values = self._values(prefix, x.state)
            if fpo:
                extras = self._fpo_draws(chain[:, -1])
                # Evaluation acts deterministically and never reads log-probs: skip the scoring pass.
                logprobs = torch.zeros_like(logprobs) if deterministic else self._fpo_scores(prefix, x.state, extras)
                return PolicyStep(actions=actions, logprobs=logprobs, values=values, extras=extras)
        return PolicyStep(actions=actions, logprobs=logprobs, values=values,
                          extras={"chain": chain, "sde_mask": mask})

    # --- Flow Policy Optimization ------------------------------------------------------------

    def _fpo_draws(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """The sampled chunk (model space) and ``fpo_samples`` flow times and noises to score it at."""
        batch, samples = action.shape[0], self.fpo_samples
        time = self.vla.model.sample_time(batch * samples, action.device).view(batch, samples)
        noise = torch.randn(batch, samples, *action.shape[1:], device=action.device)
        return {"fpo_action": action.float(), "fpo_noise": noise, "fpo_time": time}

    def _fpo_scores(self, prefix: PrefixCache, state: torch.Tensor | None,
                    extras: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Minus the flow-matching loss of the recorded chunk ``[B, chunk]``: squared velocity errors
        summed over each executed action's dims, averaged over the recorded (time, noise) draws."""
        action, noise, time = (extras[key].float() for key in FPO_KEYS)
        batch, samples = time.shape
        def repeat(tensor: torch.Tensor) -> torch.Tensor:
            return tensor.repeat_interleave(samples, dim=0)
        repeated = type(prefix)(kv=[(repeat(k), repeat(v)) for k, v in prefix.kv],
                                pad_mask=repeat(prefix.pad_mask), hidden=prefix.hidden)
        t = time.reshape(-1)
        noise, action = noise.flatten(0, 1), repeat(action)
        x_t = t[:, None, None] * noise + (1 - t[:, None, None]) * action
        velocity = self.vla.model.velocity(repeated, None if state is None else repeat(state), x_t, t).float()
        errors = self._credited((velocity - (noise - action)) ** 2)
        return -errors.view(batch, samples, -1).mean(1)

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        """Differentiable log-probs of the recorded chains (the actions are their executed part);
        with ``likelihood="fpo"``, minus the recorded chunks' flow-matching losses."""
        if self.likelihood == "fpo":
            return self._evaluate_fpo(obs, extras)
        if not extras or "chain" not in extras:
            raise ValueError("pi0.evaluate needs extras['chain'] (and 'sde_mask') from act()")
        chain = extras["chain"].detach().float()
        if chain.shape[1] != self.num_steps + 1:
            raise ValueError(f"extras['chain'] has {chain.shape[1] - 1} denoising steps, the policy {self.num_steps}")
        mask = extras.get("sde_mask")
        if mask is None:
            mask = torch.ones(chain.shape[0], self.num_steps, dtype=torch.bool, device=chain.device)
        x = self.inputs(obs)
        prefix = self._prefix(x)
        if bool((mask.sum(1) == 1).all()):  # one stochastic step a row: only its transition has a density
            return self._evaluate_one_step(prefix, x.state, chain, mask.bool().float().argmax(1), with_entropy)
        logprobs = torch.zeros(chain.shape[0], self.chunk, device=chain.device)
        entropy = torch.zeros_like(logprobs)
        for k in range(self.num_steps):
            mean, std, _ = self.transition(prefix, x.state, chain[:, k], k)
            keep = mask[:, k, None].bool()
            step = self._credited(gaussian_logprob(chain[:, k + 1], mean, std.log()))
            logprobs = logprobs + torch.where(keep, step, torch.zeros_like(step))
            if with_entropy:
                ent = self._credited(gaussian_entropy(std.log()))
                entropy = entropy + torch.where(keep, ent, torch.zeros_like(ent))
        return PolicyEval(logprobs=logprobs, entropy=entropy if with_entropy else None,
                          values=self._values(prefix, x.state))

    def _evaluate_fpo(self, obs, extras) -> PolicyEval:
        missing = [key for key in FPO_KEYS if not extras or key not in extras]
        if missing:
            raise ValueError(f"pi0.evaluate with likelihood='fpo' needs extras {missing} from act()")
        x = self.inputs(obs)
        prefix = self._prefix(x)
        return PolicyEval(logprobs=self._fpo_scores(prefix, x.state, extras), entropy=None,
                          values=self._values(prefix, x.state))

    def _evaluate_one_step(self, prefix: PrefixCache, state: torch.Tensor | None, chain: torch.Tensor,
                           steps: torch.Tensor, with_entropy: bool) -> PolicyEval:
        """:meth:`evaluate` of chains with one stochastic step a row (``sde_steps="one"``): one
        expert pass at each row's step instead of one per denoising step, the same log-probs."""
        rows = torch.arange(chain.shape[0], device=chain.device)
        mean, std, _ = self.transition(prefix, state, chain[rows, steps], steps)
        logprobs = self._credited(gaussian_logprob(chain[rows, steps + 1], mean, std.log()))
        entropy = self._credited(gaussian_entropy(std.log())) if with_entropy else None
        return PolicyEval(logprobs=logprobs, entropy=entropy, values=self._values(prefix, state))

    @property
    def demo_chunk(self) -> int:
        return self.vla.config.chunk_size

    def demo_draws(self, batch: int) -> dict[str, torch.Tensor]:
        """Flow matching's noise (padded action dims) and times, as :meth:`~.model.PiZero.loss_elements` draws them."""
        config = self.vla.config
        return {"noise": torch.randn(batch, config.chunk_size, config.max_action_dim),
                "time": self.vla.model.sample_time(batch)}

    def demo_loss(self, observation, actions, action_mask=None, draws=None) -> torch.Tensor:
        """The checkpoint's own flow-matching loss (:meth:`~infinirl.models.vla.VLA.loss`, the one SFT
        minimises) on dataset frames: the VLA's processor reads the LeRobot keys directly."""
        draws = draws or {}
        return self.vla.loss(observation, actions, noise=draws.get("noise"), time=draws.get("time"),
                             action_mask=action_mask)

    def value(self, obs) -> torch.Tensor:
        if self.value_net is None:
            raise NotImplementedError("this pi0 policy was built with value_head=False")
        x = self.inputs(obs)
        return self._values(self._prefix(x), x.state)


@POLICIES.register("pi05")
class PiZeroFivePolicy(PiZeroPolicy):
    """:class:`PiZeroPolicy` insisting on a π0.5 checkpoint."""

    family = "pi05"


@POLICIES.register("pi0_smollm2")
class PiZeroSmolLM2Policy(PiZeroPolicy):
    """:class:`PiZeroPolicy` insisting on a ``pi0_smollm2`` checkpoint (:mod:`.smollm2_vla`; its
    folder carries its sizes and tokenizer, so ``architecture`` and ``tokenizer`` are not needed)."""

    family = "pi0_smollm2"
