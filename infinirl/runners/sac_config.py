"""Typed configuration of the SAC runner (every field is a ``key=value`` CLI override).

``validate()`` checks names and numbers without starting anything (no Ray, no simulator): an
unknown env family lists the registered ones, a bad placement names the component, impossible
hyperparameters name their key. The env *task* (e.g. ``InvertedPendulum-v5``) is checked by the
runner in the driver, by building one sub-env, before any worker starts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from infinirl.config import ConfigError
from infinirl.runtime import ClusterConfig

COMPONENTS = ("collector", "learner")


@dataclass
class EnvConfig:
    name: str = "gym:InvertedPendulum-v5"
    """``family:task`` as `make_env` takes it: gym:InvertedPendulum-v5, gym:Hopper-v5, gym:Pendulum-v1, ...
    SAC needs a continuous (Box) action space and a low-dimensional observation field (`network.obs_key`)."""
    num_envs: int = 1
    """Training envs stepped together by the collector (SAC usually uses 1)."""
    num_workers: int = 0
    """0: the envs run inside the collector's process (cheapest for fast simulators); 1: every env
    runs in a subprocess of its own, so several envs simulate in parallel."""
    max_episode_steps: int | None = None
    """Extra time limit (None: the simulator's own, 1000 for the MuJoCo tasks)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options passed to the env family (for gym: keyword arguments of gymnasium.make)."""


@dataclass
class NetworkConfig:
    actor: Literal["gaussian", "flow"] = "gaussian"
    """gaussian: tanh-squashed Gaussian MLP (SAC). flow: SAC-Flow, the registered flow_matching policy
    (reparameterised through its denoising steps, path log-prob as the entropy term; docs/sac.md)."""
    flow: dict[str, Any] = field(default_factory=lambda: {"num_steps": 4, "noise_method": "flow_noise"})
    """flow_matching options when actor=flow (num_steps, noise_method, hidden, min_std, max_std, ...);
    use noise_method=flow_noise: with flow_sde the entropy term has no gradient."""
    actor_hidden: list[int] = field(default_factory=lambda: [256, 256])
    """Hidden sizes of the squashed-Gaussian actor's MLP."""
    critic_hidden: list[int] = field(default_factory=lambda: [256, 256])
    """Hidden sizes of every Q-network."""
    num_critics: int = 2
    """Q-networks in the ensemble; the target takes their minimum (2 = clipped double-Q)."""
    activation: Literal["relu", "tanh", "silu", "elu"] = "relu"
    log_std_min: float = -5.0
    log_std_max: float = 2.0
    """Range of the actor's log standard deviation (before the tanh squash)."""
    obs_key: str = "state"
    """The observation field the networks read (a flat float vector)."""


@dataclass
class AlgorithmConfig:
    gamma: float = 0.99
    """Discount per env step."""
    tau: float = 0.005
    """Polyak coefficient of the target critics: target <- (1 - tau) target + tau online."""
    batch_size: int = 256
    """Transitions per mini-batch (uniform from the replay buffer)."""
    utd_ratio: float = 1.0
    """Update-to-data ratio: gradient updates per collected env step (summed over envs), once
    learning has started. 1 is classic SAC; > 1 (e.g. 4-20) trades compute for sample efficiency."""
    learning_starts: int = 5000
    """Env steps (over all envs) of uniformly random actions before the actor acts and updates
    begin; must be >= batch_size."""
    actor_lr: float = 3.0e-4
    critic_lr: float = 1.0e-3
    alpha_lr: float = 1.0e-3
    init_alpha: float = 1.0
    """Initial entropy temperature (alpha)."""
    autotune_alpha: bool = True
    """Learn alpha so the policy's entropy tracks target_entropy (Haarnoja et al. 2018b); false keeps init_alpha."""
    target_entropy: float | None = None
    """Entropy target of the auto-tuning; None: -action_dim (the paper's heuristic)."""
    policy_delay: int = 1
    """Actor and temperature update once every N critic updates."""
    target_update_every: int = 1
    """Polyak-average the target critics once every N critic updates."""


@dataclass
class BufferConfig:
    capacity: int = 1_000_000
    """Transitions kept (a preallocated ring buffer; the oldest are overwritten first)."""


@dataclass
class EvalConfig:
    every: int = 5
    """Evaluate every N iterations (and after the last); 0 = only after the last."""
    at_start: bool = True
    """Also evaluate the initial (untrained) policy at iteration 0."""
    episodes: int = 10
    """Held-out episodes with the deterministic policy (tanh of the mean), seeds 2**31 + seed + i,
    disjoint from every training seed."""
    num_envs: int = 5
    """Envs the evaluation episodes run on, in rounds (inside the collector's process)."""
    seed: int = 0
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options for evaluation (and video) envs on top of env.kwargs."""
    target_return: float | None = None
    """Report when the held-out mean return first reaches this (summary key first_eval_at_target)."""
    video_episodes: int = 2
    """Episodes rendered into eval.mp4 after training (0 = no video)."""
    video_fps: int = 30
    video_frame_skip: int = 2
    video_max_steps: int | None = 500
    """Cut each video episode after this many steps (None: the whole episode)."""
    video_env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Simulator options of the video env on top of eval.env_kwargs, e.g. {width: 240, height: 240}
    for the gymnasium MuJoCo tasks (frame size; classic-control tasks take no such option)."""


@dataclass
class WorkerConfig:
    num_threads: int = 1
    """torch threads of the process (1 keeps small MLPs fast and results deterministic)."""


@dataclass
class LearnerConfig(WorkerConfig):
    device: Literal["auto", "cpu"] = "auto"
    """auto: the learner computes on the device its placement gives it (a GPU when placed on one,
    else the CPU); cpu: on the CPU even when placed on a GPU. The collector runs its actor on the
    CPU either way (one small batch per env step, observations in host memory)."""


@dataclass
class SACConfig:
    runner: str = "sac"
    seed: int = 0
    iterations: int = 20
    """Iterations of: collect steps_per_iteration steps per env -> add to the replay buffer ->
    utd_ratio x (new env steps) updates -> weight sync to the collector."""
    steps_per_iteration: int = 1000
    """Env steps per env per iteration. Episodes are not cut at iteration boundaries."""
    collect_ahead: bool = False
    """Pipeline collection and learning: the collector gathers iteration i+1's steps with the weights
    of iteration i while the learner trains on iteration i's batch (staleness 1 instead of 0; one
    extra iteration of steps is collected at the end and kept in the checkpoint, so resume stays exact)."""
    output_dir: str = "runs/sac"
    save_every: int = 0
    """Checkpoint (learner, replay buffer, collector state) every N iterations; 0 = only at the end."""
    keep_checkpoints: int = 2
    """Newest checkpoints kept on disk (replay buffers can be large); 0 = keep all."""
    resume: bool = True
    """Continue from the latest checkpoint in output_dir if there is one."""
    loggers: list[str] = field(default_factory=lambda: ["tensorboard"])
    env: EnvConfig = field(default_factory=EnvConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    collector: WorkerConfig = field(default_factory=WorkerConfig)
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    placement: dict[str, str] = field(default_factory=lambda: {"collector": "0", "learner": "0"})
    """collector / learner -> CPU slots or devices (one rank each). Same slots: they take turns."""
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    def validate(self) -> None:
        from infinirl.envs.registry import ENVS
        from infinirl.runners.metrics_log import KNOWN_LOGGERS
        from infinirl.runtime.placement import PlacementError, parse_spec

        family = self.env.name.partition(":")[0]
        if family not in ENVS:
            raise ConfigError(f"env.name={self.env.name!r}: unknown env family {family!r}; registered: "
                              f"{', '.join(ENVS.names())} (write family:task, e.g. gym:InvertedPendulum-v5)")
        alg = self.algorithm
        for key, value in (("iterations", self.iterations), ("steps_per_iteration", self.steps_per_iteration),
                           ("env.num_envs", self.env.num_envs), ("algorithm.batch_size", alg.batch_size),
                           ("algorithm.policy_delay", alg.policy_delay),
                           ("algorithm.target_update_every", alg.target_update_every),
                           ("network.num_critics", self.network.num_critics), ("buffer.capacity", self.buffer.capacity),
                           ("eval.episodes", self.eval.episodes), ("eval.num_envs", self.eval.num_envs),
                           ("eval.video_fps", self.eval.video_fps),
                           ("eval.video_frame_skip", self.eval.video_frame_skip)):
            if value < 1:
                raise ConfigError(f"{key}={value} must be >= 1")
        for key, value in (("save_every", self.save_every), ("keep_checkpoints", self.keep_checkpoints),
                           ("eval.every", self.eval.every), ("eval.video_episodes", self.eval.video_episodes),
                           ("eval.seed", self.eval.seed), ("collector.num_threads", self.collector.num_threads),
                           ("learner.num_threads", self.learner.num_threads)):
            if value < 0:
                raise ConfigError(f"{key}={value} must be >= 0")
        if self.env.num_workers not in (0, 1):
            raise ConfigError(f"env.num_workers={self.env.num_workers} must be 0 (envs in the collector's process) "
                              "or 1 (each env in its own subprocess)")
        if not 0 < alg.gamma <= 1:
            raise ConfigError(f"algorithm.gamma={alg.gamma} must be in (0, 1]")
        if not 0 < alg.tau <= 1:
            raise ConfigError(f"algorithm.tau={alg.tau} must be in (0, 1]")
        if alg.utd_ratio <= 0:
            raise ConfigError(f"algorithm.utd_ratio={alg.utd_ratio} must be > 0")
        for key in ("actor_lr", "critic_lr", "alpha_lr", "init_alpha"):
            if getattr(alg, key) <= 0:
                raise ConfigError(f"algorithm.{key}={getattr(alg, key)} must be > 0")
        if alg.learning_starts < alg.batch_size:
            raise ConfigError(f"algorithm.learning_starts={alg.learning_starts} must be >= algorithm.batch_size="
                              f"{alg.batch_size} (the first mini-batch needs that many transitions)")
        if self.buffer.capacity < alg.batch_size:
            raise ConfigError(f"buffer.capacity={self.buffer.capacity} must be >= "
                              f"algorithm.batch_size={alg.batch_size}")
        if any(width < 1 for width in [*self.network.actor_hidden, *self.network.critic_hidden]):
            raise ConfigError("network.actor_hidden / network.critic_hidden sizes must be >= 1")
        if not self.network.log_std_min < self.network.log_std_max:
            raise ConfigError(f"network.log_std_min={self.network.log_std_min} must be < "
                              f"network.log_std_max={self.network.log_std_max}")
        if self.network.actor == "flow":
            method = self.network.flow.get("noise_method", "flow_noise")
            if method != "flow_noise":
                raise ConfigError(f"network.flow.noise_method={method!r}: SAC-Flow needs flow_noise (a learned std); "
                                  "with flow_sde the path log-prob is a constant under reparameterisation, so the "
                                  "entropy term and the temperature would not act on the policy")
            for key in ("value_head", "chunk", "action_dim", "obs_dim", "obs_key"):
                if key in self.network.flow:
                    raise ConfigError(f"network.flow.{key} is set by the SAC runner; remove it")
        if self.eval.video_max_steps is not None and self.eval.video_max_steps < 1:
            raise ConfigError(f"eval.video_max_steps={self.eval.video_max_steps} must be >= 1 (or null)")
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
                parsed = parse_spec(spec, component)
            except PlacementError as exc:
                raise ConfigError(f"placement.{component}: {exc}") from None
            if (parsed.num_processes or 1) > 1 or (parsed.num_processes is None and len(parsed.indices) > 1):
                raise ConfigError(f"placement.{component}={spec!r}: the SAC runner runs one {component} rank; "
                                  f"give one slot or device (e.g. '0')")
