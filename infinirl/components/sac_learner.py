"""The SAC learner: networks, optimisers, the replay buffer and the update, in one component.

:class:`SACAgent` is the algorithm with no I/O and no Ray (tests drive it directly): a
:class:`~infinirl.models.sac_nets.SquashedGaussianActor`, an
:class:`~infinirl.models.sac_nets.EnsembleQ` of ``K`` critics with a Polyak-averaged target copy,
and the temperature ``alpha = exp(log_alpha)``. One :meth:`SACAgent.update` on a replay mini-batch:

1. **critics**: ``a' ~ pi(.|s')``; target ``y = r + gamma (1 - terminated) (min_k Q'_k(s', a') -
   alpha log pi(a'|s'))``; one Adam step on ``sum_k 0.5 mean (Q_k(s, a) - y)^2``
   (:func:`~infinirl.algorithms.sac.sac_critic_loss`);
2. every ``policy_delay`` updates, **actor**: ``a ~ pi(.|s)`` reparameterised, one Adam step on
   ``mean(alpha log pi(a|s) - min_k Q_k(s, a))`` with the critics frozen
   (:func:`~infinirl.algorithms.sac.sac_actor_loss`), then **temperature** (when auto-tuned): one
   step on ``-log_alpha (log pi + target_entropy)``
   (:func:`~infinirl.algorithms.sac.sac_temperature_loss`), reusing the actor step's log-probs;
3. every ``target_update_every`` updates, **targets**: ``theta' <- (1 - tau) theta' + tau theta``.

With camera frames (``SACNetSpec.encoder="cnn"``) one encoder sits in front of the actor and the
critics (:mod:`infinirl.models.sac_encoders`): the critic step trains it, the actor reads it
detached, the targets average it too, and with ``augment_pad`` every mini-batch's frames are
randomly shifted first (DrQ).

All randomness (the buffer's sampling, the reparameterisation noise, the shifts) comes from generators owned
here and saved with the checkpoint, so a resumed learner makes exactly the updates the original
would have.

:class:`SACLearnerWorker` is that agent as a runtime component: it owns the replay buffer (data
stays where it is sampled: one collected batch comes in per iteration, thousands of mini-batches
are drawn locally), serves the actor's weights to the collector (:class:`WeightSource`), and
writes checkpoints atomically.
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from infinirl.algorithms.metrics import MetricReducer
from infinirl.algorithms.sac import sac_actor_loss, sac_critic_loss, sac_temperature_loss
from infinirl.components.embodied_policy import compute_device, module_device
from infinirl.components.replay_buffer import ReplayBuffer
from infinirl.models.sac_encoders import ENCODERS, EncodedActor, EncodedCritic, random_shift_observations
from infinirl.models.sac_nets import EnsembleQ, FlowSACActor, SquashedGaussianActor
from infinirl.models.state_normalizer import EmbodimentStateNormalizer, NormalizedStateEncoder
from infinirl.runtime import WeightSource, Worker
from infinirl.utils.atomic import torch_save_atomic

__all__ = ["SACAgent", "SACLearnerWorker", "SACNetSpec", "SACUpdateSpec", "transition_fields"]

_CHECKPOINT = "learner.pt"
_BUFFER = "replay_buffer.npz"
_UPDATE_FIELDS = ("obs", "action", "reward", "next_obs", "terminated")


@dataclass(frozen=True, kw_only=True)
class SACNetSpec:
    """Network shapes and options (the collector builds the same actor from it)."""

    actor_hidden: tuple[int, ...] = (256, 256)
    critic_hidden: tuple[int, ...] = (256, 256)
    num_critics: int = 2
    activation: str = "relu"
    log_std_min: float = -5.0
    log_std_max: float = 2.0
    obs_key: str = "state"
    layer_norm: bool = False
    """A LayerNorm after every hidden layer of the Gaussian actor and the critics."""
    actor: str = "gaussian"
    """``gaussian`` (:class:`SquashedGaussianActor`) or ``flow`` (SAC-Flow, :class:`FlowSACActor`)."""
    flow: dict = field(default_factory=dict)
    """Options of the ``flow_matching`` policy when ``actor == "flow"`` (num_steps, noise_method, hidden, ...)."""
    encoder: str = "state"
    """Observation encoder (:data:`~infinirl.models.sac_encoders.ENCODERS`): ``state`` (none: the
    networks read the state vector) or ``cnn`` (camera frames + state, shared by actor and critics)."""
    encoder_options: dict = field(default_factory=dict)
    """Keyword options of the encoder (cnn: channels, strides, feature_dim)."""
    augment_pad: int = 0
    """Random-shift augmentation of the camera frames in every update (pixels, 0: none)."""
    normalize_state: bool = False
    """Normalise the state vector with running statistics per embodiment
    (:class:`~infinirl.models.state_normalizer.EmbodimentStateNormalizer`) before the encoder or the networks."""

    def build_encoder(self, obs_dim: int, cameras: dict | None = None, embodiments: int = 1):
        """The encoder module, or None (``state`` without ``normalize_state``: the networks read the
        state vector). ``embodiments``: robot kinds sharing the policy (their one-hot ends the state)."""
        encoder = ENCODERS.get(self.encoder)(obs_dim=obs_dim, cameras=cameras, **self.encoder_options)
        if not self.normalize_state:
            return encoder
        return NormalizedStateEncoder(EmbodimentStateNormalizer(obs_dim, embodiments), encoder)

    def build_actor(self, obs_dim: int, action_space, cameras: dict | None = None, embodiments: int = 1):
        """The actor; with an encoder (``cameras``: name -> (height, width)) an :class:`EncodedActor`
        that owns a fresh one."""
        encoder = self.build_encoder(obs_dim, cameras, embodiments)
        if encoder is None:
            return self._actor_head(obs_dim, action_space)
        return EncodedActor(encoder, self._actor_head(encoder.out_dim, action_space))

    def _actor_head(self, obs_dim: int, action_space):
        low = np.array(action_space.low, dtype=np.float32).reshape(-1)  # copies: Ray hands out read-only arrays
        high = np.array(action_space.high, dtype=np.float32).reshape(-1)
        if self.actor == "flow":
            return FlowSACActor(obs_dim, int(np.prod(action_space.shape)), low, high, self.obs_key, **self.flow)
        if self.actor != "gaussian":
            raise ValueError(f"SAC actor must be 'gaussian' or 'flow', got {self.actor!r}")
        return SquashedGaussianActor(obs_dim, int(np.prod(action_space.shape)), low, high, self.actor_hidden,
                                     self.log_std_min, self.log_std_max, self.activation, self.obs_key,
                                     self.layer_norm)

    def build_critic(self, obs_dim: int, action_space, encoder=None):
        """The critics; given the actor's ``encoder``, an :class:`EncodedCritic` sharing it (the
        critic loss trains it)."""
        if encoder is None:
            return EnsembleQ(obs_dim, int(np.prod(action_space.shape)), self.critic_hidden, self.num_critics,
                             self.activation, self.obs_key, self.layer_norm)
        head = EnsembleQ(encoder.out_dim, int(np.prod(action_space.shape)), self.critic_hidden, self.num_critics,
                         self.activation, self.obs_key, self.layer_norm)
        return EncodedCritic(encoder, head)


@dataclass(frozen=True, kw_only=True)
class SACUpdateSpec:
    """Hyperparameters of the update (documented on the config fields, ``infinirl/runners/sac_config.py``)."""

    gamma: float = 0.99
    tau: float = 0.005
    batch_size: int = 256
    actor_lr: float = 3e-4
    critic_lr: float = 1e-3
    alpha_lr: float = 1e-3
    init_alpha: float = 1.0
    autotune_alpha: bool = True
    target_entropy: float | None = None
    policy_delay: int = 1
    target_update_every: int = 1
    buffer_capacity: int = 1_000_000
    seed: int = 0


def transition_fields(obs_dim: int, action_dim: int) -> dict:
    """The replay buffer's fields: one row is one transition."""
    return {
        "obs": ((obs_dim,), "float32"),
        "action": ((action_dim,), "float32"),  # the actor's [-1, 1] action
        "reward": ((), "float32"),
        "next_obs": ((obs_dim,), "float32"),  # the final observation where the episode ended
        "terminated": ((), "float32"),  # 1 only for a true termination; time limits bootstrap
        "env_step": ((), "int64"),  # env steps collected before this one (sample age)
    }


class SACAgent:
    """Actor, critics (+ targets), temperature and their optimisers; :meth:`update` is one SAC step."""

    def __init__(self, net: SACNetSpec, spec: SACUpdateSpec, obs_dim: int, action_space,
                 device: torch.device | str = "cpu", cameras: dict | None = None,
                 action_mask: Callable[[Any], torch.Tensor] | None = None, embodiments: int = 1):
        torch.manual_seed(spec.seed)  # initial weights are a function of the seed, on any device
        self.net, self.spec = net, spec
        self.device = torch.device(device)
        self.action_dim = int(np.prod(action_space.shape))
        self.actor = net.build_actor(obs_dim, action_space, cameras, embodiments).to(self.device)
        # With an encoder the critics share the actor's (their loss trains it; the actor reads it detached).
        self.critic = net.build_critic(obs_dim, action_space, getattr(self.actor, "encoder", None)).to(self.device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(spec.init_alpha), dtype=torch.float32,
                                                         device=self.device))
        self.target_entropy = float(-self.action_dim if spec.target_entropy is None else spec.target_entropy)
        # ``action_mask(obs) -> [B, A]``: the action entries each sample's robot executes (a policy
        # shared by embodiments of different sizes); None: all of them.
        self.action_mask = action_mask
        actor_params = self.actor.head_parameters() if isinstance(self.actor, EncodedActor) else self.actor.parameters()
        self.actor_optim = _adam(actor_params, spec.actor_lr)
        self.critic_optim = _adam(self.critic.parameters(), spec.critic_lr)
        self.alpha_optim = _adam([self.log_alpha], spec.alpha_lr)
        noise_seed = int(np.random.SeedSequence([spec.seed, 0x1EA2]).generate_state(1)[0])
        # A CPU generator on every device: the same noise draws (copied to the device) wherever the
        # learner computes, and a checkpoint's generator state resumes on a CPU or a GPU alike.
        self.generator = torch.Generator().manual_seed(noise_seed)
        self.augment_generator = None  # random shifts of the camera frames: a stream of their own
        if net.augment_pad > 0 and isinstance(self.actor, EncodedActor):
            self.augment_generator = torch.Generator().manual_seed(
                int(np.random.SeedSequence([spec.seed, 0xA06]).generate_state(1)[0]))
        self.updates = 0

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.detach().exp()

    @property
    def state_normalizer(self) -> EmbodimentStateNormalizer | None:
        encoder = getattr(self.actor, "encoder", None)
        return encoder.normalizer if isinstance(encoder, NormalizedStateEncoder) else None

    @torch.no_grad()
    def observe_states(self, states) -> None:
        """Fold raw ``states`` ``[N, obs_dim]`` into the state normaliser's statistics (nothing
        without ``normalize_state``). The critics share the actor's normaliser; the targets' copy
        takes the same statistics (Polyak averaging moves parameters, not these)."""
        normalizer = self.state_normalizer
        if normalizer is None:
            return
        normalizer.update(torch.as_tensor(states, dtype=torch.float32).to(self.device))
        self.critic_target.encoder.normalizer.load_state_dict(normalizer.state_dict())

    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One SAC update on a mini-batch (``obs``, ``action``, ``reward``, ``next_obs``,
        ``terminated``); returns detached scalar metrics (tensors: no sync per step)."""
        spec = self.spec
        obs, next_obs = batch["obs"], batch["next_obs"]
        if self.augment_generator is not None:  # DrQ: each of obs and next_obs shifted on its own
            obs = random_shift_observations(obs, self.net.augment_pad, self.augment_generator)
            next_obs = random_shift_observations(next_obs, self.net.augment_pad, self.augment_generator)
        alpha = self.alpha
        mask = next_mask = None
        if self.action_mask is not None:
            mask, next_mask = self.action_mask(obs), self.action_mask(next_obs)
        with torch.no_grad():
            next_action, next_logprob, _ = self._sample(next_obs, next_mask)
            next_q = self.critic_target(next_obs, _masked(next_action, next_mask))
        critic = sac_critic_loss(q_values=self.critic(obs, _masked(batch["action"], mask)), rewards=batch["reward"],
                                 terminated=batch["terminated"], next_target_q_values=next_q,
                                 next_logprobs=next_logprob, alpha=alpha, gamma=spec.gamma)
        self.critic_optim.zero_grad(set_to_none=True)
        critic.loss.backward()
        self.critic_optim.step()
        metrics = {"train/critic_loss": critic.loss.detach(), "train/q_mean": critic.metrics["q_mean"],
                   "train/q_target_mean": critic.metrics["q_target_mean"],
                   "train/td_error_abs_mean": critic.metrics["td_error_abs_mean"]}
        self.updates += 1
        if self.updates % spec.policy_delay == 0:
            metrics.update(self._update_actor_and_alpha(obs, mask))
        if self.updates % spec.target_update_every == 0:
            with torch.no_grad():
                torch._foreach_lerp_(list(self.critic_target.parameters()), list(self.critic.parameters()), spec.tau)
        return metrics

    def _sample(self, obs, mask: torch.Tensor | None):
        """The actor's sample; with ``mask``, its log-prob over the executed entries where the actor
        can take a mask (the Gaussian actor; a flow's path density cannot be split)."""
        if mask is not None and getattr(self.actor, "masks_logprob", False):
            return self.actor.sample(obs, self.generator, mask=mask)
        return self.actor.sample(obs, self.generator)

    def _update_actor_and_alpha(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        self.critic.requires_grad_(False)  # the actor's gradient flows through Q into the action only
        try:
            action, logprob, _ = self._sample(obs, mask)
            actor = sac_actor_loss(logprobs=logprob, q_values=self.critic(obs, _masked(action, mask)),
                                   alpha=self.alpha)
            self.actor_optim.zero_grad(set_to_none=True)
            actor.loss.backward()
            self.actor_optim.step()
        finally:
            self.critic.requires_grad_(True)
        metrics = {"train/actor_loss": actor.loss.detach(), "train/entropy": actor.metrics["policy_entropy"]}
        if self.spec.autotune_alpha:
            target = self.target_entropy  # per sample with a mask: the same share of its executed entries
            if mask is not None and getattr(self.actor, "masks_logprob", False):
                target = self.target_entropy * mask.sum(-1) / self.action_dim
            temperature = sac_temperature_loss(log_alpha=self.log_alpha, logprobs=logprob, target_entropy=target)
            self.alpha_optim.zero_grad(set_to_none=True)
            temperature.loss.backward()
            self.alpha_optim.step()
            metrics["train/alpha_loss"] = temperature.loss.detach()
        metrics["train/alpha"] = self.alpha
        return metrics

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        return {
            "actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(), "log_alpha": self.log_alpha.detach().clone(),
            "actor_optim": self.actor_optim.state_dict(), "critic_optim": self.critic_optim.state_dict(),
            "alpha_optim": self.alpha_optim.state_dict(), "generator": self.generator.get_state(),
            "updates": self.updates,
            **({"augment_generator": self.augment_generator.get_state()} if self.augment_generator is not None else {}),
        }

    def load_state_dict(self, state: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.critic_target.load_state_dict(state["critic_target"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_optim.load_state_dict(state["actor_optim"])
        self.critic_optim.load_state_dict(state["critic_optim"])
        self.alpha_optim.load_state_dict(state["alpha_optim"])
        self.generator.set_state(state["generator"])
        if self.augment_generator is not None:
            self.augment_generator.set_state(state["augment_generator"])
        self.updates = int(state["updates"])

    def named_tensors(self):
        """Every learned tensor (for digests): actor, critics, targets, log_alpha."""
        for prefix, module in (("actor", self.actor), ("critic", self.critic), ("critic_target", self.critic_target)):
            for name, tensor in module.state_dict().items():
                yield f"{prefix}.{name}", tensor
        yield "log_alpha", self.log_alpha.detach()


def _masked(action: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """``action`` with the entries its robot does not execute zeroed (what the critics see)."""
    return action if mask is None else action * mask.to(action.dtype)


def _adam(params, lr: float) -> torch.optim.Optimizer:
    """Adam; the fused kernel where torch has it for the parameters' device (one kernel instead of a
    Python loop over SAC's many small tensors)."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr)


def _digest(named) -> str:
    h = hashlib.sha256()
    for name, tensor in named:
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


class SACLearnerWorker(Worker, WeightSource):
    """One learner rank: :class:`SACAgent` + the :class:`ReplayBuffer`, as a component."""

    def __init__(self, net: SACNetSpec, spec: SACUpdateSpec, obs_dim: int, action_space, num_threads: int = 1,
                 device: str = "auto"):
        if num_threads:
            torch.set_num_threads(num_threads)
        # Denormal floats (Adam's second moments of tiny gradients, Polyak-averaged weights) take a
        # slow microcode path on x86 CPUs; flushing them to zero keeps every update on the fast one.
        torch.set_flush_denormal(True)
        self.compute = compute_device(self.device, device)
        self.agent = SACAgent(net, spec, obs_dim, action_space, self.compute)
        self.buffer = ReplayBuffer(spec.buffer_capacity, transition_fields(obs_dim, self.agent.action_dim),
                                   seed=[spec.seed, 0xB0FF])

    def add_and_update(self, batch: dict, num_updates: int, env_steps: int) -> dict:
        """Put the collected transitions into the buffer, then run ``num_updates`` SAC updates on
        uniform mini-batches; returns the updates' mean metrics and buffer statistics."""
        import time

        metrics = self._logprob_mismatch(batch)
        self.buffer.add({name: batch[name] for name in self.buffer.fields})
        start = time.perf_counter()
        updates = MetricReducer()  # tensors until the end: no sync per update
        ages = []
        for _ in range(num_updates):
            rows = self.buffer.sample(self.agent.spec.batch_size)
            ages.append(env_steps - float(rows["env_step"].mean()))
            tensors = {name: torch.from_numpy(rows[name]).to(self.compute) for name in _UPDATE_FIELDS}
            updates.add(self.agent.update(tensors))
        seconds = time.perf_counter() - start
        metrics.update(updates.result())
        if ages:
            metrics["train/sample_age_mean"] = float(np.mean(ages))
        metrics.update({"train/updates": float(self.agent.updates), "train/updates_this_iteration": float(num_updates),
                        "train/alpha": float(self.agent.alpha), "train/buffer_size": float(len(self.buffer)),
                        "train/buffer_added": float(self.buffer.added),
                        "time/updates_per_s": num_updates / max(seconds, 1e-9)})
        return metrics

    @torch.no_grad()
    def _logprob_mismatch(self, batch: dict) -> dict:
        """Collector-vs-learner log-prob of the collector's own policy samples: 0 up to float
        rounding when both hold the same weights (the weight sync is checked every iteration)."""
        mask = np.asarray(batch.get("policy_mask", np.zeros(0, bool)), dtype=bool)
        if not mask.any():
            return {}
        obs = torch.from_numpy(np.asarray(batch["obs"])[mask]).to(self.compute)
        u = torch.from_numpy(np.asarray(batch["pre_tanh"])[mask]).to(self.compute)
        ours = self.agent.actor.logprob_of(obs, u)
        if ours is None:  # SAC-Flow: a log-prob needs the denoising path, which is not sent
            return {}
        ours = ours.cpu()
        theirs = torch.from_numpy(np.asarray(batch["logprob"])[mask])
        return {"train/logprob_mismatch": float((ours - theirs).abs().max())}

    # ------------------------------------------------------------------ weight sync / state
    def weights_for_sync(self):
        return list(self.agent.actor.state_dict().items())

    def compute_device(self) -> str:
        """Where the learner's networks are (``"cpu"``, ``"cuda:0"``), read off their parameters."""
        return str(module_device(self.agent.actor))

    def weights_digest(self) -> str:
        return _digest(self.agent.named_tensors())

    def actor_digest(self) -> str:
        return _digest(self.agent.actor.state_dict().items())

    def buffer_digest(self) -> str:
        return self.buffer.digest()

    def save_checkpoint(self, path: str) -> None:
        """Agent (weights, optimisers, generator, update count) and replay buffer, each file
        written to a temporary name and renamed into place."""
        torch_save_atomic(self.agent.state_dict(), os.path.join(path, _CHECKPOINT))
        self.buffer.save(os.path.join(path, _BUFFER))

    def load_checkpoint(self, path: str) -> None:
        # map_location: a checkpoint written on a GPU resumes on a CPU-only machine, and vice versa
        # (load_state_dict then copies each tensor onto the learner's device).
        self.agent.load_state_dict(torch.load(os.path.join(path, _CHECKPOINT), map_location="cpu", weights_only=False))
        self.buffer.load(os.path.join(path, _BUFFER))
