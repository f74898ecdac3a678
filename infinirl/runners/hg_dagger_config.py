"""Typed configuration of the HG-DAgger runner (every field is a ``key=value`` CLI override).

The robot, task, network and evaluation sections are those of the real-world SAC runner
(:mod:`infinirl.runners.realworld_sac_config`); names (driver kind, observation sources, rewards,
intervention device, demo policy) are checked against their registries before any worker starts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from infinirl.config import ConfigError, bounded
from infinirl.runners.realworld_sac_config import (
    VELOCITY_SCALE_HINT,
    VELOCITY_SCALE_KEY,
    EvalConfig,
    InterventionConfig,
    RobotConfig,
    TaskConfig,
    check_command_deadline,
    check_demo_options,
    check_single_learner,
    check_task_options,
    known_names,
    velocity_scale_resumes,
)
from infinirl.runners.run_config import RunConfig
from infinirl.runners.sac_config import NetworkConfig, WorkerConfig

__all__ = ["BCConfig", "DaggerConfig", "DaggerInterventionConfig", "HGDAggerConfig"]


@dataclass(kw_only=True)
class DaggerConfig:
    episodes_per_iteration: int = bounded(6, ge=1)
    """Episodes each robot runs per iteration with the human watching (their human-labelled steps are
    aggregated)."""
    deterministic: bool = True
    """The policy acts with tanh(mean) during the rollouts (HG-DAgger's novice acts deterministically)."""
    initial_demos: int = bounded(1, ge=0)
    """Episodes of the scripted demo policy recorded by robot rank 0 before the first iteration; the
    initial policy is cloned from them (every step labelled). Few: a weak initial policy."""
    demo_policy: str = "sawyer_goal"
    """Scripted demo policy of the initial demonstrations (infinirl/realworld/demos.py)."""
    demo_options: dict[str, Any] = field(default_factory=dict)
    """Options of the demo policy (metaworld_expert: task); checked against it before any worker starts."""
    demo_noise_std: float = bounded(0.1, ge=0)


@dataclass(kw_only=True)
class BCConfig:
    loss: Literal["mse", "gaussian_nll"] = "mse"
    """mse: (tanh(mean) - human action)^2; gaussian_nll: -log N(atanh(action); mean, std) per entry."""
    updates_per_iteration: int = bounded(300, ge=1)
    """Mini-batches on the whole aggregate after each iteration's rollouts (and on the initial demos)."""
    batch_size: int = bounded(128, ge=1)
    lr: float = bounded(1e-3, gt=0)
    weight_decay: float = bounded(0.0, ge=0)


@dataclass(kw_only=True)
class DaggerInterventionConfig(InterventionConfig):
    as_demos: bool = False
    """RLPD's (realworld_sac); refused here: every step the human gives joins the aggregate anyway."""


def _default_interventions() -> DaggerInterventionConfig:
    return DaggerInterventionConfig(device="simulated_human", options={"expert": "sawyer_goal"})


@dataclass(kw_only=True)
class HGDAggerEvalConfig(EvalConfig):
    every: int = bounded(1, ge=0)
    """Evaluation (the policy alone, no human) after every iteration by default: the learning curve."""
    at_start: bool = True
    """Evaluate the initial policy (cloned from the initial demonstrations) before the first iteration."""


@dataclass(kw_only=True)
class HGDAggerConfig(RunConfig):
    RUNNER: ClassVar[str] = "hg_dagger"
    DEFAULT_PLACEMENT: ClassVar[dict[str, str]] = {"robot": "0", "learner": "0"}
    # interventions.as_demos never had an effect here: checkpoints written when it defaulted to true resume.
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = ("robot.command_deadline_s", "robot.heartbeat_deadline_s",
                                                    "robot.max_lead_s", "learner.num_threads", "actor.num_threads",
                                                    "interventions.as_demos")

    output_dir: str = "runs/hg_dagger"
    iterations: int = bounded(10, ge=1)
    save_every: int = bounded(1, ge=0)
    keep_checkpoints: int = bounded(2, ge=0)
    robot: RobotConfig = field(default_factory=RobotConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    interventions: DaggerInterventionConfig = field(default_factory=_default_interventions)
    """The human (or simulated human) who takes over; HG-DAgger needs a device."""
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    bc: BCConfig = field(default_factory=BCConfig)
    eval: HGDAggerEvalConfig = field(default_factory=HGDAggerEvalConfig)
    actor: WorkerConfig = field(default_factory=WorkerConfig)
    """The robot workers' policy inference threads."""
    learner: WorkerConfig = field(default_factory=WorkerConfig)

    def resume_may_change(self, key: str) -> bool:
        # As in realworld_sac: a speed limit with absolute targets, the size of an action with deltas.
        if key == VELOCITY_SCALE_KEY:
            return velocity_scale_resumes([self.task])
        return super().resume_may_change(key)

    def resume_refusal_hint(self, key: str) -> str:
        return VELOCITY_SCALE_HINT if key == VELOCITY_SCALE_KEY else super().resume_refusal_hint(key)

    def check(self) -> None:
        from infinirl.realworld.demos import DEMO_POLICIES
        from infinirl.realworld.driver import ROBOT_DRIVERS
        from infinirl.realworld.robot_env import OBSERVATIONS, REWARDS

        if self.robot.fleet:
            raise ConfigError("robot.fleet: the HG-DAgger runner drives robots of one kind; leave robot.fleet empty")
        known_names(ROBOT_DRIVERS, [self.robot.kind], "robot.kind")
        ROBOT_DRIVERS.get(self.robot.kind).check_options(self.robot.kind, self.robot.options, "robot.options")
        check_command_deadline(self.robot.command_deadline_s, self.robot.kind, self.robot.options, "robot.options")
        known_names(OBSERVATIONS, self.task.observations, "task.observations")
        known_names(REWARDS, list(self.task.rewards), "task.rewards")
        check_task_options(self.task, "task")
        if not self.task.observations:
            raise ConfigError("task.observations is empty; name at least one source, e.g. [proprio]")
        if self.interventions.device is None:
            raise ConfigError("interventions.device is unset: HG-DAgger learns from a human who takes over; name a "
                              "device, e.g. interventions.device=simulated_human")
        self.interventions.check()
        if self.interventions.as_demos:
            raise ConfigError("interventions.as_demos=true feeds RLPD's demonstrations store (realworld_sac); "
                              "HG-DAgger aggregates every step the human gives already: remove it")
        if self.dagger.initial_demos:
            known_names(DEMO_POLICIES, [self.dagger.demo_policy], "dagger.demo_policy")
            check_demo_options(self.dagger.demo_policy, self.dagger.demo_options, "dagger.demo_options")
            if self.task.action_mode != "delta":
                raise ConfigError("dagger.initial_demos > 0 needs task.action_mode=delta (the scripted demo policies "
                                  "emit delta actions)")
        if self.network.actor != "gaussian" or self.network.obs_key != "state":
            raise ConfigError("network.actor must be gaussian and network.obs_key state (the state-based policy the "
                              "robot workers act with)")
        check_single_learner(self)
