"""Typed configuration of the embodied runner (every field is a ``key=value`` CLI override).

``validate()`` checks names and numbers without starting anything (no Ray, no simulator): an
unknown env family or policy lists the registered ones, a bad placement names the component. The
env *task* (e.g. the MetaWorld task name) is checked by the runner in the driver, by building one
sub-env, before any worker starts.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from infinirl.config import ConfigError
from infinirl.runtime import ClusterConfig

COMPONENTS = ("env", "rollout", "actor")


@dataclass
class EnvConfig:
    name: str = "metaworld:reach-v3"
    """``family:task`` as `make_env` takes it: metaworld:reach-v3, gym:Pendulum-v1, maniskill:PickCube-v1, ..."""
    num_envs: int = 16
    """Training envs over all env ranks (each rank gets num_envs / ranks, split into pipeline stages)."""
    num_workers: int = 0
    """Simulator subprocesses per pipeline stage of each env rank; 0 = the sub-envs run in the process
    that owns them (cheapest for fast simulators; >= 1 lets local simulation overlap inference)."""
    stage_processes: bool = False
    """With the env on its own resources: run each pipeline stage of an env rank in a process of its
    own that streams straight to the rollout, so the stages simulate in parallel (one core each) and
    no message is relayed through the env worker. Needs rollout.transport=socket."""
    max_episode_steps: int | None = None
    """Extra time limit (None: the simulator's own, 200 for MetaWorld)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options, e.g. {obs_mode: state+rgb, image_size: 64} for MetaWorld."""


@dataclass
class PolicyConfig:
    name: str = "mlp_gaussian"
    """A registered policy (mlp_gaussian, cnn_gaussian, cnn_bins, flow_matching, plugins)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """Constructor options (e.g. {hidden: [64, 64]}); shape arguments are filled from the env."""
    chunk: int = 1
    """Actions per decision (action chunking); the env executes all of them before the next decision."""
    normalize_obs: bool = True
    """Running mean/std normalisation of float observation fields (trained, synced and checkpointed with the weights)."""
    normalize_keys: list[str] = field(default_factory=list)
    """Fields to normalise; empty = every float field (state, proprio). Images are never normalised."""
    obs_clip: float = 10.0
    """Normalised observations are clipped to [-obs_clip, obs_clip]."""


@dataclass
class AlgorithmConfig:
    name: Literal["ppo", "grpo"] = "ppo"
    """ppo: GAE advantages on a learned critic (the policy's value head is trained).
    grpo: embodied GRPO, critic-free: envs run in groups of ``group_size`` reset to the same state
    (same seed); each env's first-episode return, normalised within its group, is the advantage of
    every decision of that episode, and decisions after the first episode end are masked out. Use
    ``rollout_steps`` >= the episode length (200 for MetaWorld) so the whole episode is scored."""
    group_size: int = 8
    """grpo: consecutive envs sharing a reset seed (>= 2, must divide env.num_envs)."""
    grpo_norm_by_std: bool = True
    """grpo: divide by the group's return std (False: only subtract the group mean)."""
    gamma: float = 0.99
    """Discount per decision (per chunk when chunk > 1). ppo only."""
    gae_lambda: float = 0.95
    """ppo only."""
    gae_level: Literal["chunk", "action"] = "chunk"
    """chunk: one advantage per decision (summed chunk reward); action: one per executed action
    (grpo: the episode mask then also cuts a chunk at the episode end)."""
    normalize_rewards: bool = True
    """Divide rewards by the running std of the discounted return (PPO reward scaling). ppo only:
    grpo's group normalisation makes the reward scale irrelevant."""
    epochs: int = 10
    """Passes over each iteration's batch."""
    mini_batches: int = 32
    """Optimizer steps per epoch; must divide num_envs * rollout_steps."""
    clip: float = 0.2
    """PPO ratio clip (both algorithms)."""
    value_clip: float | None = None
    """Clip the value update to +-value_clip around the rollout's value (None: no clipping). ppo only."""
    value_coef: float = 0.5
    """ppo only: grpo trains no value head (its value loss is not computed at all)."""
    entropy_coef: float = 0.0
    max_grad_norm: float = 0.5
    normalize_advantages: bool = True
    """Per mini-batch (statistics of the whole mini-batch over all ranks). ppo only: grpo's
    advantages are already normalised within each group, and are used as they are."""


@dataclass(frozen=True)
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
    "ppo": EmbodiedAlgorithm("embodied_gae", lambda a: {"gamma": a.gamma, "lam": a.gae_lambda, "level": a.gae_level},
                             critic=True, grouped=False),
    "grpo": EmbodiedAlgorithm("embodied_grpo", lambda a: {"norm_by_std": a.grpo_norm_by_std},
                              critic=False, grouped=True),
}


@dataclass
class ActorConfig:
    lr: float = 3e-4
    anneal_lr: bool = True
    """Linear decay to 0 over `iterations` (or over `actor.anneal_iterations`)."""
    anneal_iterations: int = 0
    """The decay's horizon in iterations; 0 = `iterations`, else at least `iterations`. Set it to stop
    a run early on a longer run's learning-rate schedule: a shorter `iterations=` alone decays faster
    and learns differently (push-v3: 0.62 held-out at 300 iterations annealed over 300, 0.60-0.80 at
    150 annealed over 600)."""
    adam_eps: float = 1e-5
    strategy: Literal["ddp", "fsdp"] = "ddp"
    """ddp: replicated weights, one SUM all-reduce of the gradients per step; fsdp: FSDP2 fully_shard."""
    num_threads: int = 1
    """torch threads per actor rank. 1 keeps small models fast (a 2x64 MLP's update doubles with 2
    threads on 2 cores); 0 takes every core of the host: the on-policy update runs while the envs and
    the rollout wait, so a conv net's update can use the cores they leave idle (the 64x64 pixels CNN
    on 2 cores: 6.4 -> 4.4 s an update). Meant for one actor rank per host."""
    compile: bool = False
    """torch.compile the whole optimizer step (forward, PPO loss, gradient, clipping, Adam) into fused
    kernels: ~4x faster updates of small policies on CPU, after a one-off compile of seconds to a
    minute in the first update. Needs a C++ compiler (g++/clang++). With strategy=fsdp only the
    forward pass and loss are compiled (FSDP2's hooks stay eager)."""
    device: Literal["auto", "cpu"] = "auto"
    """auto: train on the device the placement gives each rank (a GPU when placed on one, NCCL between
    ranks; else CPU); cpu: train on the CPU even when placed on a GPU (a 2x64 MLP's tiny ops are
    cheaper on CPU than as GPU kernel launches)."""


@dataclass
class RolloutConfig:
    pipeline_stages: int = 1
    """K: each env rank's envs are split into K stages; simulation of one overlaps inference of another.
    Takes effect when env and rollout are placed on disjoint resources (or with env.num_workers >= 1)."""
    transport: Literal["socket", "channel"] = "socket"
    """Env <-> rollout stream when they run in different processes (see infinirl/components/env_link.py)."""
    num_threads: int = 1
    compile: bool = False
    """torch.compile the policy's ``act`` for collection (sampling from the same random stream as
    eager, so the same seed gives the same actions up to float rounding): ~40% cheaper decisions
    for a small MLP on CPU, ~20% for the CNN, after a one-off compile of seconds in the first
    iteration. Evaluation and videos stay eager (their batch sizes vary). Needs a C++ compiler."""
    device: Literal["auto", "cpu"] = "auto"
    """auto: run the policy on the device the placement gives each rank (a GPU when placed on one);
    cpu: on the CPU even when placed on a GPU. Observations reach the policy from host memory and
    actions go back to it every step, so small state policies are often faster on CPU."""


@dataclass
class EvalConfig:
    every: int = 5
    """Held-out evaluation every N iterations (and after the last); 0 = only after the last."""
    at_start: bool = True
    """Also evaluate the initial policy (iteration 0)."""
    episodes: int = 50
    """Held-out episodes, seeds EVAL_SEED_BASE + seed + i (disjoint from every training seed)."""
    num_envs: int = 10
    """Envs the held-out episodes run on, in rounds (in the rollout's process)."""
    seed: int = 0
    deterministic: bool = True
    """Mean action (Gaussian) / most likely action instead of sampling."""
    max_episode_steps: int | None = None
    """Time limit of evaluation episodes (None: env.max_episode_steps), so training may use shorter
    episodes than the standard ones it is evaluated on."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options for the evaluation (and video) envs on top of env.kwargs, e.g.
    {terminate_on_success: true} for MetaWorld: success-at-any-step is unchanged, episodes get shorter."""
    video_episodes: int = 2
    """Episodes rendered into eval.mp4 after training (0 = no video)."""
    video_frame_skip: int = 2
    video_fps: int = 30
    video_env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options for the video env on top of eval.env_kwargs (e.g. {image_size: 128, camera: corner})."""


@dataclass
class EmbodiedConfig:
    runner: str = "embodied"
    seed: int = 0
    iterations: int = 20
    """Iterations: collect rollout_steps per env -> advantages -> PPO-clip update -> weight sync."""
    rollout_steps: int = 200
    """Decisions per env per iteration. Envs are reset (seeded) at the start of every iteration, so a
    multiple of the episode length (200 for MetaWorld) never cuts an episode."""
    output_dir: str = "runs/embodied"
    save_every: int = 0
    """Checkpoint every N iterations (0 = only at the end)."""
    resume: bool = True
    """Continue from the latest checkpoint in output_dir if there is one."""
    loggers: list[str] = field(default_factory=lambda: ["tensorboard"])
    env: EnvConfig = field(default_factory=EnvConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    placement: dict[str, str] = field(default_factory=lambda: {"env": "0", "rollout": "0", "actor": "0"})
    """env / rollout / actor -> CPU slots or devices. Same slots for env and rollout: collocated (the env
    runs inside the rollout's process); disjoint: the env has its own process and streams to the rollout."""
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    def validate(self) -> None:
        from infinirl.components.embodied_policy import registered_policies
        from infinirl.envs.registry import ENVS
        from infinirl.runners.metrics_log import KNOWN_LOGGERS
        from infinirl.runtime.placement import PlacementError, parse_spec

        family = self.env.name.partition(":")[0]
        if family not in ENVS:
            raise ConfigError(f"env.name={self.env.name!r}: unknown env family {family!r}; registered: "
                              f"{', '.join(ENVS.names())} (write family:task, e.g. metaworld:reach-v3)")
        policies = registered_policies()
        if self.policy.name not in policies:
            raise ConfigError(f"policy.name={self.policy.name!r} is not registered; registered: {', '.join(policies)}")
        for key, value in (("iterations", self.iterations), ("rollout_steps", self.rollout_steps),
                           ("env.num_envs", self.env.num_envs), ("policy.chunk", self.policy.chunk),
                           ("algorithm.epochs", self.algorithm.epochs),
                           ("algorithm.mini_batches", self.algorithm.mini_batches),
                           ("rollout.pipeline_stages", self.rollout.pipeline_stages),
                           ("eval.episodes", self.eval.episodes), ("eval.num_envs", self.eval.num_envs),
                           ("eval.video_frame_skip", self.eval.video_frame_skip)):
            if value < 1:
                raise ConfigError(f"{key}={value} must be >= 1")
        for key, value in (("env.num_workers", self.env.num_workers), ("save_every", self.save_every),
                           ("eval.every", self.eval.every), ("eval.video_episodes", self.eval.video_episodes),
                           ("eval.seed", self.eval.seed), ("actor.num_threads", self.actor.num_threads),
                           ("actor.anneal_iterations", self.actor.anneal_iterations),
                           ("rollout.num_threads", self.rollout.num_threads)):
            if value < 0:
                raise ConfigError(f"{key}={value} must be >= 0")
        if self.actor.lr <= 0:
            raise ConfigError(f"actor.lr={self.actor.lr} must be > 0")
        if self.actor.anneal_lr and 0 < self.actor.anneal_iterations < self.iterations:
            raise ConfigError(f"actor.anneal_iterations={self.actor.anneal_iterations} < iterations={self.iterations}: "
                              "the learning rate would reach 0 before the run ends and the rest would not train; "
                              "set actor.anneal_iterations >= iterations (0 = iterations)")
        if not 0 < self.algorithm.gamma <= 1 or not 0 <= self.algorithm.gae_lambda <= 1:
            raise ConfigError("algorithm.gamma must be in (0, 1] and algorithm.gae_lambda in [0, 1]")
        if not 0 < self.algorithm.clip < 1:
            raise ConfigError(f"algorithm.clip={self.algorithm.clip} must be in (0, 1)")
        if self.algorithm.name not in ALGORITHMS:
            raise ConfigError(f"algorithm.name={self.algorithm.name!r}; choose from {', '.join(ALGORITHMS)}")
        if ALGORITHMS[self.algorithm.name].grouped:
            size, envs = self.algorithm.group_size, self.env.num_envs
            if size < 2:
                raise ConfigError(f"algorithm.group_size={size} must be >= 2 for algorithm.name="
                                  f"{self.algorithm.name} (a group compares envs reset to the same state)")
            if envs % size:
                raise ConfigError(f"algorithm.group_size={size} does not divide env.num_envs={envs}: envs run in "
                                  f"groups of algorithm.group_size sharing a reset seed; pick a divisor of "
                                  f"env.num_envs or set env.num_envs to a multiple of {size}")
        if self.env.stage_processes and self.rollout.transport != "socket":
            raise ConfigError(f"env.stage_processes=true streams each stage over its own socket; "
                              f"rollout.transport={self.rollout.transport} is not supported with it: set "
                              "rollout.transport=socket or env.stage_processes=false")
        for key, wanted in (("actor.compile", self.actor.compile), ("rollout.compile", self.rollout.compile)):
            if wanted:
                _check_compile(key)
        batch = self.env.num_envs * self.rollout_steps
        if batch % self.algorithm.mini_batches:
            raise ConfigError(f"algorithm.mini_batches={self.algorithm.mini_batches} does not divide the batch of "
                              f"env.num_envs*rollout_steps={batch} decisions; pick a divisor")
        for name in self.loggers:
            if name not in KNOWN_LOGGERS:
                raise ConfigError(f"loggers: unknown logger '{name}'; choose from {', '.join(KNOWN_LOGGERS)}")
        unknown = set(self.placement) - set(COMPONENTS)
        missing = set(COMPONENTS) - set(self.placement)
        if unknown or missing:
            raise ConfigError(f"placement must name exactly {', '.join(COMPONENTS)}; "
                              f"unknown {sorted(unknown)}, missing {sorted(missing)}")
        for component, spec in self.placement.items():
            try:
                parse_spec(spec, component)
            except PlacementError as exc:
                raise ConfigError(f"placement.{component}: {exc}") from None


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
