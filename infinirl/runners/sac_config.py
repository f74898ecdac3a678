"""Typed configuration of the SAC runner (every field is a ``key=value`` CLI override).

Field limits are declared on the fields; :meth:`SACConfig.check` holds the rules that involve
several fields. The env *task* (e.g. ``InvertedPendulum-v5``) is checked by the runner in the
driver, by building one sub-env, before any worker starts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from infinirl.config import ConfigError, bounded
from infinirl.runners.run_config import RunConfig
from infinirl.runners.sim_config import SimEnvConfig, SimEvalConfig

COMPONENTS = ("collector", "learner")


@dataclass(kw_only=True)
class EnvConfig(SimEnvConfig):
    name: str = "gym:InvertedPendulum-v5"
    """``family:task``: gym:InvertedPendulum-v5, gym:Hopper-v5, gym:Pendulum-v1, ... SAC needs a
    continuous (Box) action space and a low-dimensional observation field (`network.obs_key`)."""
    num_workers: int = bounded(0, ge=0, le=1)
    """0: the envs run inside the collector's process (cheapest for fast simulators); 1: every env
    runs in a subprocess of its own, so several envs simulate in parallel."""


@dataclass(kw_only=True)
class NetworkConfig:
    actor: Literal["gaussian", "flow"] = "gaussian"
    """gaussian: tanh-squashed Gaussian MLP (SAC). flow: SAC-Flow, the registered flow_matching policy
    (reparameterised through its denoising steps, path log-prob as the entropy term; docs/sac.md)."""
    flow: dict[str, Any] = field(default_factory=lambda: {"num_steps": 4, "noise_method": "flow_noise"})
    """flow_matching options when actor=flow (num_steps, noise_method, hidden, min_std, max_std, ...);
    use noise_method=flow_noise: with flow_sde the entropy term has no gradient."""
    actor_hidden: list[int] = bounded(default_factory=lambda: [256, 256], ge=1, each=True)
    """Hidden sizes of the squashed-Gaussian actor's MLP."""
    critic_hidden: list[int] = bounded(default_factory=lambda: [256, 256], ge=1, each=True)
    """Hidden sizes of every Q-network."""
    num_critics: int = bounded(2, ge=1)
    """Q-networks in the ensemble; the target takes their minimum (2 = clipped double-Q)."""
    activation: Literal["relu", "tanh", "silu", "elu"] = "relu"
    log_std_min: float = -5.0
    log_std_max: float = 2.0
    """Range of the actor's log standard deviation (before the tanh squash)."""
    obs_key: str = "state"
    """The observation field the networks read (a flat float vector)."""
    layer_norm: bool = False
    """A LayerNorm after every hidden layer of the actor and the critics (RLPD/DSRL): keeps Q from
    diverging at high update-to-data ratios or with wide, unnormalised inputs (a VLA's features).
    With actor=flow, the critics only (the actor is the flow policy's network)."""

    def check_flow(self) -> None:
        """The SAC-Flow actor's options (``actor=flow``): a learned noise std, and none of the keys the
        runner sets itself."""
        method = self.flow.get("noise_method", "flow_noise")
        if method != "flow_noise":
            raise ConfigError(f"network.flow.noise_method={method!r}: SAC-Flow needs flow_noise (a learned std); "
                              "with flow_sde the path log-prob is a constant under reparameterisation, so the "
                              "entropy term and the temperature would not act on the policy")
        for key in ("value_head", "chunk", "action_dim", "obs_dim", "obs_key"):
            if key in self.flow:
                raise ConfigError(f"network.flow.{key} is set by the SAC runner; remove it")


@dataclass(kw_only=True)
class AlgorithmConfig:
    gamma: float = bounded(0.99, gt=0, le=1)
    """Discount per env step."""
    tau: float = bounded(0.005, gt=0, le=1)
    """Polyak coefficient of the target critics: target <- (1 - tau) target + tau online."""
    batch_size: int = bounded(256, ge=1)
    """Transitions per mini-batch (uniform from the replay buffer)."""
    utd_ratio: float = bounded(1.0, gt=0)
    """Update-to-data ratio: gradient updates per collected env step (summed over envs), once
    learning has started. 1 is classic SAC; > 1 (e.g. 4-20) trades compute for sample efficiency."""
    learning_starts: int = bounded(5000, ge=0)
    """Env steps (over all envs) of uniformly random actions before the actor acts and updates
    begin; must be >= batch_size."""
    actor_lr: float = bounded(3.0e-4, gt=0)
    critic_lr: float = bounded(1.0e-3, gt=0)
    alpha_lr: float = bounded(1.0e-3, gt=0)
    init_alpha: float = bounded(1.0, gt=0)
    """Initial entropy temperature (alpha)."""
    autotune_alpha: bool = True
    """Learn alpha so the policy's entropy tracks target_entropy (Haarnoja et al. 2018b); false keeps init_alpha."""
    target_entropy: float | None = None
    """Entropy target of the auto-tuning; None: -action_dim (the paper's heuristic)."""
    policy_delay: int = bounded(1, ge=1)
    """Actor and temperature update once every N critic updates."""
    target_update_every: int = bounded(1, ge=1)
    """Polyak-average the target critics once every N critic updates."""


@dataclass(kw_only=True)
class BufferConfig:
    capacity: int = bounded(1_000_000, ge=1)
    """Transitions kept (a preallocated ring buffer; the oldest are overwritten first)."""


@dataclass(kw_only=True)
class EvalConfig(SimEvalConfig):
    video_max_steps: int | None = bounded(500, ge=1)
    """Cut each video episode after this many steps (None: the whole episode)."""
    headline: Literal["return_mean", "success_rate"] = "return_mean"
    """The held-out metric the summary, the target and the progress bar follow (success_rate for
    tasks with a success flag, e.g. MetaWorld)."""


@dataclass(kw_only=True)
class WorkerConfig:
    num_threads: int = bounded(1, ge=0)
    """torch threads of the process (1 keeps small MLPs fast and results deterministic)."""


@dataclass(kw_only=True)
class LearnerConfig(WorkerConfig):
    device: Literal["auto", "cpu"] = "auto"
    """auto: the learner computes on the device its placement gives it (a GPU when placed on one,
    else the CPU); cpu: on the CPU even when placed on a GPU. The collector runs its actor on the
    CPU either way (one small batch per env step, observations in host memory)."""


@dataclass(kw_only=True)
class SACConfig(RunConfig):
    RUNNER: ClassVar[str] = "sac"
    DEFAULT_PLACEMENT: ClassVar[dict[str, str]] = {"collector": "0", "learner": "0"}
    RENAMED_KEYS: ClassVar[dict[str, str]] = {"eval.target_return": "eval.target"}
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = ("env.num_workers", "env.step_timeout_s", "env.max_restarts",
                                                    "collector.num_threads", "learner.num_threads", "learner.device")

    output_dir: str = "runs/sac"
    keep_checkpoints: int = bounded(2, ge=0)
    """Newest checkpoints kept on disk (replay buffers can be large); 0 = keep all."""
    steps_per_iteration: int = bounded(1000, ge=1)
    """Env steps per env per iteration. Episodes are not cut at iteration boundaries."""
    collect_ahead: bool = False
    """Pipeline collection and learning: the collector gathers iteration i+1's steps with the weights
    of iteration i while the learner trains on iteration i's batch (staleness 1 instead of 0; one
    extra iteration of steps is collected at the end and kept in the checkpoint, so resume stays exact)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    collector: WorkerConfig = field(default_factory=WorkerConfig)
    learner: LearnerConfig = field(default_factory=LearnerConfig)

    def data_files(self) -> dict[str, str]:
        # The frozen VLA's weights and statistics decide the features the networks learn on.
        checkpoint = self.env.vla_checkpoint()
        return {"env.kwargs.vla.checkpoint": checkpoint} if checkpoint else {}

    def check(self) -> None:
        alg = self.algorithm
        if alg.learning_starts < alg.batch_size:
            raise ConfigError(f"algorithm.learning_starts={alg.learning_starts} must be >= algorithm.batch_size="
                              f"{alg.batch_size} (the first mini-batch needs that many transitions)")
        if self.buffer.capacity < alg.batch_size:
            raise ConfigError(f"buffer.capacity={self.buffer.capacity} must be >= "
                              f"algorithm.batch_size={alg.batch_size}")
        if not self.network.log_std_min < self.network.log_std_max:
            raise ConfigError(f"network.log_std_min={self.network.log_std_min} must be < "
                              f"network.log_std_max={self.network.log_std_max}")
        if self.network.actor == "flow":
            self.network.check_flow()
        self._check_single_ranks()

    def _check_single_ranks(self) -> None:
        from infinirl.runtime.placement import parse_spec

        # Under auto the scheduler's SAC model places one rank of each component it places.
        pinned = self.pinned_placement()
        for component in COMPONENTS:
            if component not in pinned:
                continue
            spec = pinned[component]
            parsed = parse_spec(spec, component)
            if (parsed.num_processes or 1) > 1 or (parsed.num_processes is None and len(parsed.indices) > 1):
                raise ConfigError(f"placement.{component}={spec!r}: the SAC runner runs one {component} rank; "
                                  f"give one slot or device (e.g. '0')")
