"""Typed configuration of the embodied runner (every field is a ``key=value`` CLI override).

Field limits are declared on the fields; :meth:`EmbodiedConfig.check` holds the rules that involve
several fields (no Ray, no simulator). The env *task* (e.g. the MetaWorld task name) and the env
options are checked by the runner in the driver, before any worker starts.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from infinirl.config import ConfigError, bounded
from infinirl.engines.policy_lora import PolicyLoraSpec
from infinirl.runners.async_rollout import AsyncConfig
from infinirl.runners.run_config import RunConfig
from infinirl.runners.sim_config import SimEnvConfig, SimEvalConfig
from infinirl.runtime.scaling import ScalingConfig

COMPONENTS = ("env", "rollout", "actor")


@dataclass(kw_only=True)
class EnvConfig(SimEnvConfig):
    name: str = "metaworld:reach-v3"
    num_envs: int = bounded(16, ge=1)
    """Training envs over all env ranks (each rank gets num_envs / ranks, split into pipeline stages)."""
    num_workers: int = bounded(0, ge=0)
    """Simulator subprocesses per pipeline stage of each env rank; 0 = the sub-envs run in the process
    that owns them (cheapest for fast simulators; >= 1 lets local simulation overlap inference)."""
    stage_processes: bool = False
    """With the env on its own resources: run each pipeline stage of an env rank in a process of its
    own that streams straight to the rollout, so the stages simulate in parallel (one core each) and
    no message is relayed through the env worker. Needs rollout.transport=socket."""


@dataclass(kw_only=True)
class PolicyConfig:
    name: str = "mlp_gaussian"
    """A registered policy (mlp_gaussian, cnn_gaussian, cnn_bins, flow_matching, plugins)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """Constructor options (e.g. {hidden: [64, 64]}); shape arguments are filled from the env."""
    chunk: int = bounded(1, ge=1)
    """Actions per decision (action chunking); the env executes all of them before the next decision."""
    normalize_obs: bool | None = None
    """Running mean/std normalisation of float observation fields (trained, synced and checkpointed
    with the weights). None: on, except for policies that normalise their own inputs (the VLAs, with
    their checkpoint's statistics), for which true is refused (it would normalise twice)."""
    normalize_keys: list[str] = field(default_factory=list)
    """Fields to normalise; empty = every float field (state, proprio). Images are never normalised."""
    obs_clip: float = bounded(10.0, gt=0)
    """Normalised observations are clipped to [-obs_clip, obs_clip]."""


@dataclass(kw_only=True)
class BCAnchorConfig:
    """PPO's behaviour-cloning anchor (DAPG's cloning term; :mod:`infinirl.components.demo_anchor`):
    every policy step of the update also minimises the policy's cloning loss on demonstrations."""

    data: str | None = None
    """A LeRobotDataset folder of demonstrations (e.g. the one `infinirl train sft_vla_metaworld`
    generated and cloned the policy on); None: no anchor. The policy must have a ``demo_loss``
    (the VLA families)."""
    coef: float = bounded(1.0, gt=0)
    """The cloning loss's weight beside the PPO loss, in iteration 0."""
    decay: float = bounded(1.0, gt=0, le=1)
    """The weight's factor per iteration (``coef * decay**iteration``; DAPG decays it, 1 keeps it)."""
    batch_size: int = bounded(32, ge=1)
    """Dataset frames per optimizer step (over all actor ranks)."""
    augment_shift: int = bounded(0, ge=0)
    """Shift the frames' images by up to this many pixels (the SFT runner's ``data.augment_shift``)."""
    camera_key: str | None = None
    """The dataset's camera (``observation.images.<name>``); None: its only one."""


@dataclass(kw_only=True)
class AlgorithmConfig:
    name: Literal["ppo", "grpo"] = "ppo"
    """ppo: GAE advantages on a learned critic (the policy's value head is trained).
    grpo: embodied GRPO, critic-free: envs run in groups of ``group_size`` reset to the same state
    (same seed); each env's first-episode return, normalised within its group, is the advantage of
    every decision of that episode, and decisions after the first episode end are masked out. Use
    ``rollout_steps`` >= the episode length (200 for MetaWorld) so the whole episode is scored."""
    group_size: int = bounded(8, ge=2)
    """grpo: consecutive envs sharing a reset seed (>= 2, must divide env.num_envs)."""
    grpo_norm_by_std: bool = True
    """grpo: divide by the group's return std (False: only subtract the group mean)."""
    grpo_baseline: bool = True
    """grpo: subtract the group's mean return. False: the raw first-episode return is the advantage
    (REINFORCE without a baseline, with ``grpo_norm_by_std=false``): with success as the reward
    (``env.kwargs.reward_mode=sparse``) only the decisions of successful episodes are reinforced and
    failed ones are left alone rather than pushed away."""
    grpo_per_episode: bool = False
    """grpo: every episode weighs the same in the update, whatever its length (each env's advantages
    scaled by the mean first-episode length over its own). The policy loss averages over decisions,
    so otherwise a task whose solved episodes are long outweighs one solved in a few decisions."""
    gamma: float = bounded(0.99, gt=0, le=1)
    """Discount per decision: per chunk when chunk > 1 with gae_level=chunk, per executed action with
    gae_level=action. ppo only."""
    gae_lambda: float = bounded(0.95, ge=0, le=1)
    """ppo only."""
    gae_level: Literal["chunk", "action"] = "chunk"
    """chunk: one advantage per decision (summed chunk reward); action: one per executed action
    (grpo: the episode mask then also cuts a chunk at the episode end)."""
    normalize_rewards: bool = True
    """Divide rewards by the running std of the discounted return (PPO reward scaling). ppo only:
    grpo's group normalisation makes the reward scale irrelevant."""
    epochs: int = bounded(10, ge=1)
    """Passes over each iteration's batch."""
    mini_batches: int = bounded(32, ge=1)
    """Optimizer steps per epoch; must divide num_envs * rollout_steps."""
    clip: float = bounded(0.2, gt=0, lt=1)
    """PPO ratio clip (both algorithms)."""
    value_clip: float | None = bounded(None, gt=0)
    """Clip the value update to +-value_clip around the rollout's value (None: no clipping). ppo only."""
    value_coef: float = bounded(0.5, ge=0)
    """ppo only: grpo trains no value head (its value loss is not computed at all)."""
    entropy_coef: float = bounded(0.0, ge=0)
    max_grad_norm: float = bounded(0.5, gt=0)
    normalize_advantages: bool = True
    """Per mini-batch (statistics of the whole mini-batch over all ranks). ppo only: grpo's
    advantages are already normalised within each group, and are used as they are."""
    normalize_advantages_per_task: bool = False
    """ppo on a multi-task env: each iteration's advantages normalised within each task (mean 0,
    std 1 over that task's envs) before the per-mini-batch normalisation, so every task pulls the
    shared policy as hard, whatever the scale of its shaped reward. Refused with grpo (its groups
    share a task and are normalised already)."""
    asynchronous: AsyncConfig = field(default_factory=AsyncConfig)
    """Collect the next iterations' trajectories while the actor trains, up to `max_staleness`
    weight versions ahead (docs/embodied.md#asynchronous-training)."""
    is_cap: float | None = bounded(None, gt=0)
    """Decoupled PPO: recompute the batch's log-probs under the actor's current weights (the
    proximal policy) and weight each decision by pi_proximal / pi_rollout, capped here; None: the
    rollout's log-probs are PPO's old policy (on-policy)."""
    is_cap_mode: Literal["truncate", "mask"] = "truncate"
    """truncate: TIS, min(w, is_cap). mask: decisions with w > is_cap get no policy gradient."""
    critic_warmup: int = bounded(0, ge=0)
    """ppo: the first `critic_warmup` iterations train the critic only; the policy's weights stay
    exactly as they are. A new value head on a pretrained policy predicts nothing yet: without the
    warm-up the first policy updates follow advantages of an unfitted critic."""
    bc: BCAnchorConfig = field(default_factory=BCAnchorConfig)
    """Clone demonstrations beside the policy gradient (off unless ``bc.data`` is set)."""


@dataclass(frozen=True, kw_only=True)
class EmbodiedAlgorithm:
    """What the runner and the trainer do differently per ``algorithm.name`` (see ALGORITHMS)."""

    advantage: str
    """Estimator in ``infinirl.algorithms.ADVANTAGES``."""
    advantage_kwargs: Callable[[AlgorithmConfig], dict]
    """Its hyperparameters, from the config."""
    critic: bool
    """Trains the value head (value loss; explained variance is logged)."""
    grouped: bool
    """Envs come in groups of ``algorithm.group_size`` reset with one seed, and the advantages are
    normalised within a group: no reward scaling, no per-mini-batch advantage normalisation."""


ALGORITHMS: dict[str, EmbodiedAlgorithm] = {
    "ppo": EmbodiedAlgorithm(advantage="embodied_gae",
                             advantage_kwargs=lambda a: {"gamma": a.gamma, "lam": a.gae_lambda, "level": a.gae_level},
                             critic=True, grouped=False),
    "grpo": EmbodiedAlgorithm(advantage="embodied_grpo", advantage_kwargs=lambda a: {"norm_by_std": a.grpo_norm_by_std,
                                                                      "baseline": a.grpo_baseline,
                                                                      "per_episode": a.grpo_per_episode},
                              critic=False, grouped=True),
}


@dataclass(kw_only=True)
class ActorConfig:
    lr: float = bounded(3e-4, gt=0)
    value_lr: float | None = bounded(None, gt=0)
    """Learning rate of the policy's critic (its value head; with lora, under ``lora.train_fully``);
    None: ``lr``. A new value head on a pretrained policy that trains at a small ``lr`` needs a larger
    one to follow the returns (RLinf trains π0 at 1e-5 beside a value head at 1e-4). Annealed with
    ``lr``; not with ``compile`` (its fused step has one learning rate)."""
    anneal_lr: bool = True
    """Linear decay to 0 over `iterations` (or over `actor.anneal_iterations`)."""
    anneal_iterations: int = bounded(0, ge=0)
    """The decay's horizon in iterations; 0 = `iterations`, else at least `iterations`. Set it to stop
    a run early on a longer run's learning-rate schedule: a shorter `iterations=` alone decays faster
    and learns differently."""
    desired_kl: float | None = bounded(None, gt=0)
    """Adaptive learning rate (rsl_rl's schedule for robot PPO): after every mini-batch the rate is
    divided by 1.5 when PPO's approximate KL to the rollout policy is above 2 x `desired_kl` and
    multiplied by 1.5 below half of it, within 1/100 and 10 times `lr` (every group alike, the
    value head's too; on top of `anneal_lr`'s decay). Keeps each update's step in the trust region
    whatever the gradient's noise; None: the rate follows `lr` and `anneal_lr` only. Not with
    `compile`. Logged as `train/lr` and `train/kl_scale`."""
    warmup_steps: int = bounded(0, ge=0)
    """Ramp the rate linearly over each parameter group's first `warmup_steps` optimizer steps (the
    k-th step at k / `warmup_steps` of the rate; counted from Adam's own step count, so a resumed run
    continues the ramp). Adam's first step moves every weight by about the full rate whatever the
    gradient's size: on a pretrained policy (a VLA's action expert) that one step can leave PPO's
    trust region (approximate KL 0.5-1). 0: no ramp. Not with `compile`."""
    adam_eps: float = bounded(1e-5, gt=0)
    strategy: Literal["ddp", "fsdp"] = "ddp"
    """ddp: replicated weights, one SUM all-reduce of the gradients per step; fsdp: FSDP2 fully_shard."""
    num_threads: int = bounded(1, ge=0)
    """torch threads per actor rank. 1 keeps small models fast (a small MLP's many tiny ops only pay
    for waking a second thread); 0 takes every core of the host: the on-policy update runs while the
    envs and the rollout wait, so a conv net's update can use the cores they leave idle. Meant for
    one actor rank per host."""
    compile: bool = False
    """torch.compile the whole optimizer step (forward, PPO loss, gradient, clipping, Adam) into fused
    kernels: much faster updates of small policies on CPU, whose eager cost is per-op overhead, after
    a one-off compile of seconds to a minute in the first update. Needs a C++ compiler (g++/clang++).
    With strategy=fsdp only the forward pass and loss are compiled (FSDP2's hooks stay eager). Refused
    in the driver for a policy that trains bf16/fp16 weights (their Adam keeps float32 masters)."""
    device: Literal["auto", "cpu"] = "auto"
    """auto: train on the device the placement gives each rank (a GPU when placed on one, NCCL between
    ranks; else CPU); cpu: train on the CPU even when placed on a GPU (a 2x64 MLP's tiny ops are
    cheaper on CPU than as GPU kernel launches)."""
    lora: PolicyLoraSpec | None = None
    """Low-rank adapters on the policy's linear layers (a VLA's backbone; docs/vla.md): only they and
    ``lora.train_fully`` (the value head) train; the rollout receives the merged weights. None: every
    weight trains."""


@dataclass(kw_only=True)
class RolloutConfig:
    pipeline_stages: int = bounded(1, ge=1)
    """K: each env rank's envs are split into K stages; simulation of one overlaps inference of another.
    Takes effect when env and rollout are placed on disjoint resources (or with env.num_workers >= 1)."""
    transport: Literal["socket", "channel"] = "socket"
    """Env <-> rollout stream when they run in different processes (see infinirl/components/env_link.py)."""
    num_threads: int = bounded(1, ge=0)
    compile: bool = False
    """torch.compile the policy's ``act`` for collection (sampling from the same random stream as
    eager, so the same seed gives the same actions up to float rounding): cheaper decisions for
    small policies on CPU, after a one-off compile of seconds in the first
    iteration. Evaluation and videos stay eager (their batch sizes vary). Needs a C++ compiler."""
    device: Literal["auto", "cpu"] = "auto"
    """auto: run the policy on the device the placement gives each rank (a GPU when placed on one);
    cpu: on the CPU even when placed on a GPU. Observations reach the policy from host memory and
    actions go back to it every step, so small state policies are often faster on CPU."""


@dataclass(kw_only=True)
class EvalConfig(SimEvalConfig):
    episodes: int = bounded(50, ge=1)
    num_envs: int = bounded(10, ge=1)
    """Envs the held-out episodes run on, in rounds (in the rollout's process)."""
    target: float | None = 0.9
    """The summary names the first evaluation whose success rate reached this."""
    deterministic: bool = True
    """Mean action (Gaussian) / most likely action instead of sampling."""
    max_episode_steps: int | None = bounded(None, ge=1)
    """Time limit of evaluation episodes (None: env.max_episode_steps), so training may use shorter
    episodes than the standard ones it is evaluated on."""


@dataclass(kw_only=True)
class EmbodiedConfig(RunConfig):
    RUNNER: ClassVar[str] = "embodied"
    DEFAULT_PLACEMENT: ClassVar[dict[str, str]] = {"env": "0", "rollout": "0", "actor": "0"}
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = (
        "env.num_workers", "env.stage_processes", "env.step_timeout_s", "env.max_restarts",
        "rollout.pipeline_stages", "rollout.transport",
        "rollout.num_threads", "rollout.compile", "rollout.device", "actor.num_threads", "actor.compile",
        "actor.device", "scaling")

    output_dir: str = "runs/embodied"
    rollout_steps: int = bounded(200, ge=1)
    """Decisions per env per iteration. Envs are reset (seeded) at the start of every iteration, so a
    multiple of the episode length (200 for MetaWorld) never cuts an episode."""
    env: EnvConfig = field(default_factory=EnvConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    scaling: ScalingConfig = field(default_factory=ScalingConfig)
    """Online scaling of the env component (env and rollout on disjoint slots): a command file and/or
    a policy on the env ranks' busy ratio (see infinirl.runtime.scaling)."""

    def data_files(self) -> dict[str, str]:
        # The demonstrations the cloning anchor draws from, the checkpoint the policy starts from (its
        # statistics are read again on resume), and a frozen VLA folded into the env.
        paths = {"algorithm.bc.data": self.algorithm.bc.data, "policy.kwargs.checkpoint":
                 self.policy.kwargs.get("checkpoint"), "env.kwargs.vla.checkpoint": self.env.vla_checkpoint()}
        return {key: path for key, path in paths.items() if isinstance(path, str) and path}

    def _anneals_over_iterations(self) -> bool:
        return self.actor.anneal_lr and not self.actor.anneal_iterations

    def resume_may_change(self, key: str) -> bool:
        # The learning rate's decay horizon is `iterations` here: the checkpoint's iterations ran on the
        # old schedule, so a new length would half-apply a different one.
        if key == "iterations" and self._anneals_over_iterations():
            return False
        return super().resume_may_change(key)

    def resume_refusal_hint(self, key: str) -> str:
        if key == "iterations" and self._anneals_over_iterations():
            return ("the learning rate decays to 0 over iterations (actor.anneal_lr with actor.anneal_iterations=0); "
                    "to make a run extendable, start it with actor.anneal_iterations set to its final length")
        return super().resume_refusal_hint(key)

    def _check_groups(self) -> None:
        if ALGORITHMS[self.algorithm.name].grouped and self.env.num_envs % self.algorithm.group_size:
            size, envs = self.algorithm.group_size, self.env.num_envs
            raise ConfigError(f"algorithm.group_size={size} does not divide env.num_envs={envs}: envs run in "
                              f"groups of algorithm.group_size sharing a reset seed; pick a divisor of "
                              f"env.num_envs or set env.num_envs to a multiple of {size}")
        if not self.algorithm.grpo_baseline and self.algorithm.grpo_norm_by_std:
            raise ConfigError("algorithm.grpo_baseline=false keeps the raw returns, which dividing by the group's "
                              "std would rescale per group; set algorithm.grpo_norm_by_std=false with it")

    def _policy_normalizes_own_inputs(self) -> bool:
        from infinirl.models.policies.base import POLICIES

        return bool(getattr(POLICIES.get(self.policy.name), "normalizes_own_inputs", False))

    def normalizes_obs(self) -> bool:
        """Whether the runner's running normaliser applies (``policy.normalize_obs``, None resolved)."""
        if self.policy.normalize_obs is None:
            return not self._policy_normalizes_own_inputs()
        return self.policy.normalize_obs

    def _check_normalizer(self) -> None:
        if self.policy.normalize_obs and self._policy_normalizes_own_inputs():
            raise ConfigError(f"policy.normalize_obs=true: policy {self.policy.name} normalises its own inputs (its "
                              "checkpoint's statistics), a running normaliser would do it twice; set "
                              "policy.normalize_obs=false")

    def check(self) -> None:
        from infinirl.components.embodied_policy import registered_policies

        try:
            self.scaling.check()
            if self.actor.lora is not None:
                self.actor.lora.check()
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

        policies = registered_policies()
        if self.policy.name not in policies:
            raise ConfigError(f"policy.name={self.policy.name!r} is not registered; registered: {', '.join(policies)}")
        self._check_normalizer()
        if self.actor.anneal_lr and 0 < self.actor.anneal_iterations < self.iterations:
            raise ConfigError(f"actor.anneal_iterations={self.actor.anneal_iterations} < iterations={self.iterations}: "
                              "the learning rate would reach 0 before the run ends and the rest would not train; "
                              "set actor.anneal_iterations >= iterations (0 = iterations)")
        per_step_rates = {"actor.desired_kl": self.actor.desired_kl is not None,
                          "actor.warmup_steps": bool(self.actor.warmup_steps)}
        if self.algorithm.bc.data is not None and self.actor.compile:
            raise ConfigError("algorithm.bc.data adds a cloning loss to each step, which actor.compile's fused step "
                              "(the PPO loss alone) cannot; set actor.compile=false or remove algorithm.bc.data")
        for key in (key for key, used in per_step_rates.items() if used and self.actor.compile):
            raise ConfigError(f"{key} changes the learning rate at every step, which actor.compile's fused step "
                              f"(its rate fixed when compiled) cannot; set actor.compile=false or remove {key}")
        self._check_groups()
        if self.env.stage_processes and self.rollout.transport != "socket":
            raise ConfigError(f"env.stage_processes=true streams each stage over its own socket; "
                              f"rollout.transport={self.rollout.transport} is not supported with it: set "
                              "rollout.transport=socket or env.stage_processes=false")
        for key, wanted in (("actor.compile", self.actor.compile), ("rollout.compile", self.rollout.compile)):
            if wanted:
                _check_compile(key)
        if self.algorithm.asynchronous.partial_rollout:
            raise ConfigError("algorithm.asynchronous.partial_rollout is for language-model generation (a policy "
                              "decision has no generation to interrupt); remove it")
        batch = self.env.num_envs * self.rollout_steps
        if batch % self.algorithm.mini_batches:
            raise ConfigError(f"algorithm.mini_batches={self.algorithm.mini_batches} does not divide the batch of "
                              f"env.num_envs*rollout_steps={batch} decisions; pick a divisor")


def find_cxx_compiler() -> str | None:
    """The C++ compiler torch.compile's CPU kernels can be built with ($CXX, g++, c++, clang++), or None."""
    for name in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        path = shutil.which(name) if name else None
        if path:
            return path
    return None


def _check_compile(key: str) -> None:
    """``actor.compile`` / ``rollout.compile`` are checked in the driver: a missing compiler would
    otherwise surface as an inductor build error inside a worker, in the middle of the first iteration."""
    if find_cxx_compiler() is None:
        raise ConfigError(f"{key}=true needs a C++ compiler for torch.compile's CPU kernels, and none of "
                          "$CXX, g++, c++, clang++ is on PATH: install one (Debian: apt-get install g++) "
                          f"or set {key}=false")
