"""Typed configuration of the real-world SAC runner (every field is a ``key=value`` CLI override).

Names (driver kind, observation sources, reward components, demo policy) are checked against
their registries in :meth:`RealWorldSACConfig.check`, before any worker starts; the robot's
observation size is known only once a robot worker has connected to its robot.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from infinirl.config import ConfigError, bounded
from infinirl.runners.run_config import EvalSchedule, RunConfig
from infinirl.runners.sac_config import AlgorithmConfig, LearnerConfig, NetworkConfig, WorkerConfig

__all__ = ["CNNConfig", "EdgeLinkConfig", "EvalConfig", "InterventionConfig", "RealWorldNetworkConfig",
           "RealWorldSACConfig", "RobotConfig", "TaskConfig", "check_demo_options", "check_single_learner",
           "check_task_options", "known_names", "parse_address"]


@dataclass(kw_only=True)
class FleetEntry:
    kind: str
    """Driver kind of this robot rank."""
    options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of its driver."""
    task: dict[str, Any] = field(default_factory=dict)
    """Its task keys over the shared ``task`` section (e.g. its own observations and rewards)."""


@dataclass(kw_only=True)
class RobotConfig:
    kind: str = "sim_sawyer"
    """Driver kind (``infinirl robots --kinds``: sim_sawyer, sim_so101, so101_feetech, plugins). A rank
    placed on a discovered robot (``placement.robot: robot:0``) drives that robot instead."""
    options: dict[str, Any] = field(default_factory=lambda: {"task": "reach-v3", "control_hz": 20.0,
                                                              "image_size": None})
    """Keyword options of the driver (``make_robot(kind, **options)``)."""
    velocity_scale: float = bounded(0.5, gt=0, le=1)
    """Safety: fraction of the robot's top speed a command may ask for."""
    max_lead_s: float | None = bounded(0.1, gt=0)
    """Safety: a joint (or end-effector) target may lead the measured pose by at most what the robot's
    top speed covers in this time, so a blocked or lagging joint cannot collect a target it would jump
    to when it clears (None: off; raise it for an arm whose load makes it sag further)."""
    command_deadline_s: float | None = bounded(0.5, gt=0)
    """Safety: hold the robot when no command came within this (None: off)."""
    heartbeat_deadline_s: float | None = bounded(2.0, gt=0)
    """Safety: stop the robot when its control loop gave no sign of life within this (None: off)."""
    fleet: list[FleetEntry] = field(default_factory=list)
    """Heterogeneous runs: one entry per robot rank (placement.robot gives as many ranks), each its own
    kind, options and task keys; kind/options above are then unused. Robots of different shapes share
    one policy: observations padded to the largest plus a one-hot of the robot kind, actions padded to
    the largest (each robot executes its own first entries)."""


@dataclass(kw_only=True)
class TaskConfig:
    observations: list[str] = field(default_factory=lambda: ["proprio", "sim_state"])
    """State vector sources, concatenated in order: proprio, ee_position, sim_state, block_position."""
    cameras: list[str] = field(default_factory=list)
    """Cameras recorded as pixels into the replay store; network.encoder=cnn reads them, the state
    encoder does not."""
    camera_names: dict[str, str] = field(default_factory=dict)
    """Camera -> the name its frames carry in the policy and the replay store, where it differs:
    robots of a fleet with different cameras (e.g. the Sawyer's corner, the SO-101's front) give
    them one name, with one task.frame_size, so one encoder and one store field serve both."""
    frame_size: list[int] | None = None
    """[height, width]: every camera frame is resized to it at the robot before the policy, the replay
    store or the link sees it (the training resolution; a camera streaming 480x640 keeps its raw
    frames at the robot). None: frames as the camera gives them."""
    rewards: dict[str, float] = field(default_factory=lambda: {"goal_distance": 1.0, "success": 1.0})
    """Reward component -> weight: success, goal_distance, block_distance, classifier (a learned
    success classifier: docs/realworld.md)."""
    reward_options: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Options of the reward components that take some, e.g. ``classifier: {path: runs/clf/reach.pt,
    threshold: 0.5, terminate_on_success: true}``."""
    max_episode_steps: int = bounded(50, ge=1)
    """Steps (control periods) before an episode is cut (it still bootstraps)."""
    action_mode: Literal["delta", "absolute"] = "delta"
    """delta: actions move the target by up to the safe step per period; absolute: actions span the command bounds."""
    terminate_on_success: bool = True


@dataclass(kw_only=True)
class PipelineConfig:
    mode: Literal["async", "sync"] = "async"
    """async: robots act at their own rate with the latest weights while the learner updates
    continuously; sync: the same components take turns (collect an episode, then update)."""
    iteration_s: float = bounded(10.0, gt=0)
    """Wall-clock seconds of one iteration (robot time cannot be sped up; iterations are time windows)."""
    publish_every: int = bounded(20, ge=1)
    """async: the learner publishes its actor as a new version every N updates."""
    max_updates_per_step: float | None = bounded(None, gt=0)
    """async: cap of learner updates per stored transition (None: update as fast as the learner can)."""
    max_staleness: int | None = bounded(None, ge=0)
    """Versions a step may lag the learner when it arrives (None: no bound)."""
    staleness_action: Literal["drop", "log"] = "drop"
    """What happens to an episode whose steps lag more than max_staleness: drop it (counted) or keep and log it."""
    sync_poll_s: float = bounded(0.2, gt=0)
    """async: how often the driver looks for a newer published version to send to the robots."""
    durable: bool = True
    """fsync every stored episode (survives power loss); false still survives a killed process."""
    transport: Literal["ray", "edge"] = "ray"
    """How robot and learner talk. ray: the robot is a worker of the run's Ray cluster (channels and
    weight syncs); edge: the robot runs at an edge node that dials the trainer over the mutual-TLS link
    of infinirl.edge (episodes up through its spool, weights down as deltas; the ``edge`` section)."""


@dataclass(kw_only=True)
class EdgeLinkConfig:
    listen: str = "0.0.0.0:7443"
    """pipeline.transport=edge: HOST:PORT where the trainer's hub accepts the edge (port 0: any free
    port, for an edge node launched here)."""
    certs: str | None = None
    """Folder made by ``python -m infinirl.edge certs <folder> --edges <name>``: the trainer reads
    ca.pem, cloud.pem, cloud.key; the edge node ca.pem, <name>.pem, <name>.key."""
    name: str = "edge-0"
    """The edge's name: the common name of its certificate."""
    launch: bool = False
    """Start the edge node on this machine as a process of its own (one-machine runs, tests, demos);
    false: run ``python -m infinirl.edge robot ...`` on the robot's machine (docs/edge.md)."""
    dial: str | None = None
    """launch: HOST:PORT the edge node launched here dials (None: the hub's port on 127.0.0.1); e.g.
    a link emulator in front of the hub."""
    spool: str | None = None
    """The edge's on-disk outbox of unacknowledged episodes (None: <output_dir>/edge/spool)."""
    spool_gib: float = bounded(2.0, gt=0)
    """The spool's bound; beyond it a finished episode is refused (counted as spool_refused, logged)."""
    connect_timeout_s: float = bounded(300.0, gt=0)
    """How long the trainer waits for the edge to connect, and a robot call for its answer."""
    drain_s: float = bounded(60.0, gt=0)
    """When the robot stops, how long the edge waits for the trainer to acknowledge its spool."""
    frame_format: Literal["jpeg", "png"] = "jpeg"
    """How camera frames travel (png: lossless)."""
    jpeg_quality: int = bounded(90, ge=1, le=100)
    heartbeat_s: float = bounded(1.0, gt=0)
    """Either end sends a heartbeat after this long without sending."""
    dead_after_s: float = bounded(6.0, gt=0)
    """Either end closes the link after this long without receiving (the edge then reconnects)."""
    page_listen: str | None = None
    """HOST:PORT where the trainer serves the edge robot's intervention page (``interventions.device:
    web`` at the edge) through the link, so people open it at the trainer while the edge opens no port
    (port 0: any free port; the address is printed). The page's token is its only guard: keep HOST
    local (127.0.0.1) or on a trusted network. None: not served."""
    max_offline_s: float = bounded(30.0, ge=0)
    """How long the edge's robot acts on its last weights once the link is down (counted from when
    the link is declared down, dead_after_s after it went silent); beyond it the robot holds (the
    driver's hold) until the link returns."""

    def check(self, transport: str) -> None:
        if transport != "edge":
            return
        addresses = {"edge.listen": self.listen, "edge.dial": self.dial, "edge.page_listen": self.page_listen}
        for key, value in addresses.items():
            if value is not None:
                parse_address(value, key)
        if self.certs is None:
            raise ConfigError("pipeline.transport=edge needs edge.certs: a folder made by `python -m infinirl.edge "
                              f"certs <folder> --edges {self.name}`")

    def check_trainer_files(self) -> None:
        """The trainer's certificate files (and the edge's when it launches the edge node); checked
        where the trainer starts, not in :meth:`check`, since the edge holds other files."""
        names = ["ca.pem", "cloud.pem", "cloud.key", *([f"{self.name}.pem", f"{self.name}.key"] if self.launch else [])]
        missing = [n for n in names if not os.path.isfile(os.path.join(self.certs, n))]
        if missing:
            raise ConfigError(f"edge.certs={self.certs!r} lacks {', '.join(missing)}; create the folder with "
                              f"`python -m infinirl.edge certs {self.certs} --edges {self.name}`")


def parse_address(text: str, key: str) -> tuple[str, int]:
    """``(host, port)`` of ``HOST:PORT``; a one-line ConfigError naming ``key`` otherwise."""
    host, _, port = str(text).rpartition(":")
    if not host or not port.isdigit() or int(port) > 65535:
        raise ConfigError(f"{key}={text!r}: expected HOST:PORT, e.g. 0.0.0.0:7443")
    return host, int(port)


@dataclass(kw_only=True)
class CNNConfig:
    channels: list[int] = bounded(default_factory=lambda: [32, 32, 32], ge=1, each=True)
    """Output channels of each 3x3 conv layer (one trunk per camera; ReLU between)."""
    strides: list[int] = bounded(default_factory=lambda: [2, 2, 1], ge=1, each=True)
    """Stride of each conv layer (one per entry of channels)."""
    feature_dim: int = bounded(64, ge=1)
    """Image features after the projection (Linear, LayerNorm, tanh); the state is concatenated after them."""
    augment_pad: int = bounded(4, ge=0)
    """Random-shift augmentation (DrQ) of every mini-batch's frames by up to this many pixels (0: off)."""


@dataclass(kw_only=True)
class RealWorldNetworkConfig(NetworkConfig):
    encoder: str = "state"
    """Observation encoder: state (the networks read the state vector) or cnn (a conv stack over the
    task.cameras frames, the state concatenated after it; the critic loss trains it, the actor reads
    it detached)."""
    cnn: CNNConfig = field(default_factory=CNNConfig)
    """The cnn encoder's shape and augmentation (network.encoder=cnn)."""
    normalize_state: bool = False
    """Normalise the state vector before the networks with running mean and variance kept per robot
    kind (a fleet of different robots: each kind's entries with its own statistics; the kind one-hot
    passes through). The learner folds in every stored episode; the statistics travel with the weights."""

    def check(self, cameras: list[str], key: str = "task.cameras") -> None:
        from infinirl.models.sac_encoders import ENCODERS

        known_names(ENCODERS, [self.encoder], "network.encoder")
        if self.actor == "flow":
            self.check_flow()
        if self.obs_key != "state":
            raise ConfigError(f"network.obs_key={self.obs_key!r}: robot observations are read from 'state'")
        if self.encoder == "cnn":
            if not cameras:
                raise ConfigError(f"network.encoder=cnn reads camera frames but {key} is empty; name a camera, e.g. "
                                  f"{key}=[corner] (and give a simulated robot robot.options.image_size=64)")
            if len(self.cnn.channels) != len(self.cnn.strides):
                raise ConfigError(f"network.cnn.channels ({len(self.cnn.channels)} layers) and network.cnn.strides "
                                  f"({len(self.cnn.strides)}) need one entry per conv layer")

    def encoder_spec(self) -> dict:
        """The encoder keywords of :class:`~infinirl.components.sac_learner.SACNetSpec`."""
        if self.encoder != "cnn":
            return {"encoder": self.encoder}
        cnn = self.cnn
        return {"encoder": "cnn", "augment_pad": cnn.augment_pad,
                "encoder_options": {"channels": tuple(cnn.channels), "strides": tuple(cnn.strides),
                                    "feature_dim": cnn.feature_dim}}


@dataclass(kw_only=True)
class DemoConfig:
    episodes: int = bounded(0, ge=0)
    """RLPD: demonstrations recorded once (by robot rank 0, with the scripted policy) into
    <output_dir>/demos before training; 0 turns demonstrations off."""
    policy: str = "sawyer_goal"
    """Scripted demo policy: sawyer_goal, metaworld_expert (infinirl/realworld/demos.py)."""
    options: dict[str, Any] = field(default_factory=dict)
    """Options of the demo policy (metaworld_expert: task)."""
    noise_std: float = bounded(0.1, ge=0)
    """Gaussian noise on the demo actions (in [-1, 1] units), for coverage around the expert's path."""
    fraction: float = bounded(0.5, ge=0, le=1)
    """Share of each mini-batch drawn from the demonstrations (RLPD: 0.5)."""


@dataclass(kw_only=True)
class InterventionConfig:
    device: str | None = None
    """Intervention device of every robot: keyboard, gamepad, simulated_human (a scripted expert that
    takes over when the policy drifts), plugins; None: no human. Intervened steps are stored with
    their flag and the human's (executed) action."""
    options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of the device (keyboard: path, axis_keys; gamepad: path, axes, takeover_button;
    simulated_human: expert, threshold, reaction_steps, correct_steps, seed; docs/realworld.md)."""
    as_demos: bool = True
    """RLPD: the intervened stretches of each episode also go into the demonstrations buffer (the
    whole episode goes into the online store as always)."""
    reward: Literal["env", "human"] = "env"
    """env: the task's rewards; human: the human's success / failure marks are the reward (1 / 0 on
    the step that led to the marked state, which ends the episode; 0 elsewhere)."""
    labels: bool = False
    """Save each marked episode's observations with success labels under <output_dir>/success_labels
    (one .npz per episode, on the robot's node), for training a success classifier."""

    def check(self) -> None:
        from infinirl.realworld.intervention import INTERVENTION_DEVICES

        if self.device is not None:
            known_names(INTERVENTION_DEVICES, [self.device], "interventions.device")
        elif self.reward == "human" or self.labels:
            raise ConfigError("interventions.reward=human and interventions.labels need a device that gives marks; "
                              "set interventions.device")


@dataclass(kw_only=True)
class EvalConfig(EvalSchedule):
    at_start: bool = False
    """An evaluation of the untrained policy costs robot time; off by default."""
    episodes: int = bounded(5, ge=1)
    """Episodes of the deterministic policy on every robot per evaluation (not stored, not trained on)."""
    target: float | None = bounded(0.8, ge=0, le=1)
    """Success rate the summary reports the first evaluation reaching."""
    video_episodes: int = bounded(1, ge=0)
    """After training, deterministic episodes of robot rank 0 filmed by its first camera into
    ``<output_dir>/eval.mp4`` at the control rate (0 = none; a robot without a camera records none
    and the run says why)."""


@dataclass(kw_only=True)
class ReplayConfig:
    path: str | None = None
    """Replay store folder; None: <output_dir>/replay."""
    cache_mb: int = bounded(1024, ge=0)


@dataclass(kw_only=True)
class RealWorldSACConfig(RunConfig):
    RUNNER: ClassVar[str] = "realworld_sac"
    DEFAULT_PLACEMENT: ClassVar[dict[str, str]] = {"robot": "0", "learner": "0"}
    # robot.velocity_scale: only with absolute actions (resume_may_change)
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = ("pipeline.mode", "pipeline.iteration_s", "pipeline.sync_poll_s",
                                                    "pipeline.max_updates_per_step", "robot.command_deadline_s",
                                                    "robot.heartbeat_deadline_s", "robot.max_lead_s",
                                                    "learner.num_threads", "learner.device", "actor.num_threads",
                                                    "pipeline.transport", "edge")

    output_dir: str = "runs/realworld_sac"
    iterations: int = bounded(20, ge=1)
    save_every: int = bounded(1, ge=0)
    keep_checkpoints: int = bounded(2, ge=0)
    robot: RobotConfig = field(default_factory=RobotConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    network: RealWorldNetworkConfig = field(default_factory=RealWorldNetworkConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    demos: DemoConfig = field(default_factory=DemoConfig)
    interventions: InterventionConfig = field(default_factory=InterventionConfig)
    """A human (or simulated one) who takes over the robots during training episodes."""
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    edge: EdgeLinkConfig = field(default_factory=EdgeLinkConfig)
    """The link to a robot at the edge (pipeline.transport=edge)."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    actor: WorkerConfig = field(default_factory=WorkerConfig)
    """The robot workers' policy inference threads."""
    learner: LearnerConfig = field(default_factory=lambda: LearnerConfig(device="cpu"))
    """The learner's torch threads and device: cpu (default: the state networks' small MLPs), or auto (the
    GPU its placement gives it, e.g. placement.learner=0 on a GPU machine; what a cnn encoder wants)."""

    def resume_may_change(self, key: str) -> bool:
        if key == VELOCITY_SCALE_KEY:
            return velocity_scale_resumes([self.task_of(i) for i in range(len(self.robot.fleet))] or [self.task])
        return super().resume_may_change(key)

    def resume_refusal_hint(self, key: str) -> str:
        return VELOCITY_SCALE_HINT if key == VELOCITY_SCALE_KEY else super().resume_refusal_hint(key)

    def check(self) -> None:
        from infinirl.realworld.demos import DEMO_POLICIES
        from infinirl.realworld.driver import ROBOT_DRIVERS
        from infinirl.realworld.robot_env import OBSERVATIONS, REWARDS

        known_names(ROBOT_DRIVERS, [self.robot.kind], "robot.kind")
        if not self.robot.fleet:
            ROBOT_DRIVERS.get(self.robot.kind).check_options(self.robot.kind, self.robot.options, "robot.options")
            check_command_deadline(self.robot.command_deadline_s, self.robot.kind, self.robot.options,
                                   "robot.options")
        for index, entry in enumerate(self.robot.fleet):
            known_names(ROBOT_DRIVERS, [entry.kind], f"robot.fleet[{index}].kind")
            ROBOT_DRIVERS.get(entry.kind).check_options(entry.kind, entry.options, f"robot.fleet[{index}].options")
            check_command_deadline(self.robot.command_deadline_s, entry.kind, entry.options,
                                   f"robot.fleet[{index}].options")
            task = self.task_of(index)
            known_names(OBSERVATIONS, task.observations, f"robot.fleet[{index}].task.observations")
            known_names(REWARDS, list(task.rewards), f"robot.fleet[{index}].task.rewards")
            check_task_options(task, f"robot.fleet[{index}].task")
        known_names(OBSERVATIONS, self.task.observations, "task.observations")
        known_names(REWARDS, list(self.task.rewards), "task.rewards")
        check_task_options(self.task, "task")
        self.interventions.check()
        if not self.task.observations:
            raise ConfigError("task.observations is empty; name at least one source, e.g. [proprio]")
        if self.demos.episodes:
            known_names(DEMO_POLICIES, [self.demos.policy], "demos.policy")
            check_demo_options(self.demos.policy, self.demos.options, "demos.options")
            if self.task.action_mode != "delta":
                raise ConfigError("demos.episodes > 0 needs task.action_mode=delta (the scripted demo policies "
                                  "emit delta actions)")
        alg = self.algorithm
        if alg.learning_starts < alg.batch_size:
            raise ConfigError(f"algorithm.learning_starts={alg.learning_starts} must be >= algorithm.batch_size="
                              f"{alg.batch_size} (the first mini-batch needs that many transitions)")
        self.network.check(self.task.cameras)
        for index in range(len(self.robot.fleet)):
            self.network.check(self.task_of(index).cameras, f"robot.fleet[{index}].task.cameras")
        self._check_placement()
        self._check_transport()

    def _check_transport(self) -> None:
        if self.pipeline.transport == "edge":
            if self.pipeline.mode != "async":
                raise ConfigError(f"pipeline.transport=edge runs pipeline.mode=async only (got "
                                  f"{self.pipeline.mode!r}); set pipeline.mode=async or pipeline.transport=ray")
            if self.robot.fleet:
                raise ConfigError("pipeline.transport=edge drives one robot at one edge; robot.fleet needs "
                                  "pipeline.transport=ray")
        self.edge.check(self.pipeline.transport)
        serves_page = self.pipeline.transport == "edge" and self.edge.page_listen is not None
        if serves_page and self.interventions.device != "web":
            raise ConfigError(f"edge.page_listen serves the edge's web intervention page, but interventions.device is "
                              f"{self.interventions.device!r}; set interventions.device=web or drop edge.page_listen")

    def task_of(self, index: int) -> TaskConfig:
        """The task of fleet entry ``index``: the shared section with the entry's keys over it."""
        from dataclasses import asdict

        from infinirl.config import to_dataclass

        return to_dataclass(TaskConfig, {**asdict(self.task), **self.robot.fleet[index].task},
                            f"robot.fleet[{index}].task")

    def _check_placement(self) -> None:
        check_single_learner(self)


_DEMO_ARGUMENTS_OF_THE_RUNNER = ("env", "seed", "noise_std")
"""What :func:`~infinirl.realworld.demos.make_demo_policy` passes a demo policy itself."""


VELOCITY_SCALE_KEY = "robot.velocity_scale"
VELOCITY_SCALE_HINT = ("with task.action_mode=delta an action moves the target by up to robot.velocity_scale times "
                       "the top speed per control period, so the policy and the stored actions were learned at the "
                       "old scale; keep it, or run with task.action_mode=absolute, where it only limits speed")


def velocity_scale_resumes(tasks: list[TaskConfig]) -> bool:
    """Whether a new ``robot.velocity_scale`` takes effect as intended on resume: only when every
    robot's actions are absolute targets (the scale then only caps how fast the robot gets there);
    a delta action is a step of the scale's size, so the learned policy would act differently."""
    return all(task.action_mode == "absolute" for task in tasks)


def check_demo_options(policy: str, options: dict, key: str) -> None:
    """The options of a registered scripted demo policy against its constructor, so that a misspelt
    one is a ConfigError naming it here rather than a TypeError in a robot worker."""
    import inspect

    from infinirl.realworld.demos import DEMO_POLICIES

    signature = inspect.signature(DEMO_POLICIES.get(policy))
    named = [name for name, p in signature.parameters.items() if name not in _DEMO_ARGUMENTS_OF_THE_RUNNER
             and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    for name in options:
        if name in _DEMO_ARGUMENTS_OF_THE_RUNNER:
            raise ConfigError(f"{key}.{name}: the runner passes the robot env, the run's seed and the demo noise "
                              f"itself; remove {name} from {key}")
    try:
        signature.bind_partial(**options)
    except TypeError as exc:
        unknown = [name for name in options if name not in signature.parameters]
        where = f"{key}.{unknown[0]}: not an option of" if unknown else f"{key}: {exc} for"
        raise ConfigError(f"{where} demo policy {policy!r}; its options: {', '.join(named) or 'none'}") from None


def check_command_deadline(deadline_s: float | None, kind: str, options: dict, where: str) -> None:
    """``robot.command_deadline_s`` must exceed the robot's control period: the control loop sends one
    command per period, so a shorter deadline makes the watchdog hold the robot between any two steps."""
    import inspect

    from infinirl.realworld.driver import ROBOT_DRIVERS

    if deadline_s is None:
        return
    control_hz = options.get("control_hz")
    if control_hz is None:  # the driver's own default
        parameter = inspect.signature(ROBOT_DRIVERS.get(kind).driver_class().__init__).parameters.get("control_hz")
        control_hz = None if parameter is None or parameter.default is inspect.Parameter.empty else parameter.default
    if control_hz and deadline_s <= 1.0 / float(control_hz):
        raise ConfigError(f"robot.command_deadline_s={deadline_s} must be longer than the control period "
                          f"1/{where}.control_hz = {1.0 / float(control_hz):g} s")


def check_single_learner(cfg: RunConfig) -> None:
    """The robot runners' learner is one rank on one device or CPU slot (where the config places it;
    the scheduler places it by the same rule)."""
    from infinirl.runtime.placement import parse_spec

    if "learner" not in cfg.pinned_placement():
        return  # placed by the scheduler, by these rules, when the run starts
    learner = parse_spec(cfg.placement["learner"], "learner")
    if learner.kind == "robots" or (learner.num_processes or 1) > 1 or (learner.num_processes is None
                                                                         and len(learner.indices) > 1):
        raise ConfigError(f"placement.learner={cfg.placement['learner']!r}: the learner is one rank on one "
                          "device or CPU slot (e.g. '0')")


def known_names(registry, names, key: str) -> None:
    """A one-line ConfigError naming ``key`` for a name ``registry`` does not hold."""
    for name in names:
        if name not in registry:
            raise ConfigError(f"{key}: unknown {registry.kind} {name!r}; registered: {', '.join(registry.names())}")


def check_task_options(task: TaskConfig, key: str) -> None:
    """The reward components' options as the robot env will take them (unknown, missing or orphan
    options), the camera names and the frame size, checked before any worker starts."""
    from infinirl.realworld.robot_env import RobotEnvSpec

    try:
        RobotEnvSpec(rewards=dict(task.rewards), reward_options=dict(task.reward_options))
    except ValueError as exc:
        raise ConfigError(f"{key}.reward_options: {exc}") from None
    try:
        RobotEnvSpec(cameras=tuple(task.cameras), camera_names=dict(task.camera_names))
    except ValueError as exc:
        raise ConfigError(f"{key}.camera_names: {exc}") from None
    size = task.frame_size
    if size is not None and (len(size) != 2 or not all(isinstance(v, int) and v > 0 for v in size)):
        raise ConfigError(f"{key}.frame_size={list(size)}: give [height, width], two positive ints (e.g. [64, 64]), "
                          "or null for frames as the camera gives them")
