"""The robot driver interface (hardware abstraction layer), the driver registry and discovery.

A :class:`RobotDriver` is one physical (or simulated) robot: it says what it is (:class:`RobotSpec`),
reports what it senses (:class:`RobotObservation`) and takes position targets. Everything above it
(the safety layer, the env adapter, the robot worker) programs against this class only, so a
simulated arm and the real one it stands for are exchanged by changing the driver kind.

Commands are flat float vectors whose meaning the spec's ``control_mode`` gives:

* ``"joint_position"``: ``[q_1 .. q_dof]`` target joint angles (radians), then the gripper target if
  the robot has one;
* ``"ee_position"``: ``[x, y, z]`` end-effector target (metres, robot base frame), then the gripper.

The gripper target is ``0`` (closed) to ``1`` (open) on every robot. ``spec.action_low`` /
``spec.action_high`` bound each entry; the safety filter (:mod:`~infinirl.realworld.safety`) clips to
them, to the joint limits or workspace box, and to the velocity limit before a driver sees a command.

Driver kinds are registered in :data:`ROBOT_DRIVERS` (entry-point group ``infinirl.robots``, so an
installed package adds a kind without touching this file). Each kind reports the robots it can reach
from this node (:meth:`DriverKind.attached`); :func:`discover` asks every kind, which is what cluster
start runs on each node to build the ``robot:N`` inventory.
"""

from __future__ import annotations

import abc
import importlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from infinirl.registry import Registry

__all__ = [
    "CONTROL_MODES",
    "ROBOT_DRIVERS",
    "AttachedRobot",
    "CameraSpec",
    "DriverKind",
    "RobotDriver",
    "RobotError",
    "RobotObservation",
    "RobotSpec",
    "RobotStoppedError",
    "discover",
    "make_robot",
]

CONTROL_MODES = ("joint_position", "ee_position")
ControlMode = Literal["joint_position", "ee_position"]
EE_DIMS = 3  # end-effector commands are positions; orientation is the robot's own business


class RobotError(RuntimeError):
    """A robot could not do what was asked (link lost, device refused, not connected)."""


class RobotStoppedError(RobotError):
    """A command reached a robot that was stopped; ``reset()`` (or ``connect()``) re-arms it."""


@dataclass(frozen=True, kw_only=True)
class CameraSpec:
    """One camera a robot streams: ``frames[name]`` is uint8 ``height x width x 3``."""

    name: str
    height: int
    width: int


def _as_vector(value: Any, name: str, size: int | None = None) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    if size is not None and array.shape != (size,):
        raise ValueError(f"RobotSpec.{name} must have {size} entries, got {array.shape[0]}")
    return array


@dataclass(frozen=True, kw_only=True, eq=False)
class RobotSpec:
    """What a robot is: its kind, joints, rate, command layout and limits.

    ``joint_low`` / ``joint_high`` / ``max_joint_velocity`` (rad/s) have ``dof`` entries (the arm
    joints, the gripper excluded). ``workspace_low`` / ``workspace_high`` bound the end effector
    (metres, robot base frame) and ``max_ee_speed`` its speed (m/s); both may be ``None`` for a
    robot whose end effector is not known. ``action_low`` / ``action_high`` bound a command
    (``command_size`` entries, see the module docstring).
    """

    kind: str
    dof: int
    control_hz: float
    control_mode: ControlMode
    action_low: np.ndarray
    action_high: np.ndarray
    joint_low: np.ndarray
    joint_high: np.ndarray
    max_joint_velocity: np.ndarray
    workspace_low: np.ndarray | None = None
    workspace_high: np.ndarray | None = None
    max_ee_speed: float | None = None
    cameras: tuple[CameraSpec, ...] = ()
    has_gripper: bool = False
    joint_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.control_mode not in CONTROL_MODES:
            raise ValueError(f"RobotSpec.control_mode must be one of {CONTROL_MODES}, got {self.control_mode!r}")
        if self.control_hz <= 0:
            raise ValueError(f"RobotSpec.control_hz must be positive, got {self.control_hz}")
        for name in ("joint_low", "joint_high", "max_joint_velocity"):
            object.__setattr__(self, name, _as_vector(getattr(self, name), name, self.dof))
        for name in ("action_low", "action_high"):
            object.__setattr__(self, name, _as_vector(getattr(self, name), name, self.command_size))
        if (self.workspace_low is None) != (self.workspace_high is None):
            raise ValueError("RobotSpec.workspace_low and workspace_high must be given together")
        if self.workspace_low is not None:
            object.__setattr__(self, "workspace_low", _as_vector(self.workspace_low, "workspace_low", EE_DIMS))
            object.__setattr__(self, "workspace_high", _as_vector(self.workspace_high, "workspace_high", EE_DIMS))
        if self.control_mode == "ee_position" and (self.workspace_low is None or self.max_ee_speed is None):
            raise ValueError("an ee_position robot needs workspace_low/high and max_ee_speed")
        if self.joint_names and len(self.joint_names) != self.dof:
            raise ValueError(f"RobotSpec.joint_names has {len(self.joint_names)} names for {self.dof} joints")
        for low, high, name in ((self.action_low, self.action_high, "action"), (self.joint_low, self.joint_high,
                                                                               "joint")):
            if np.any(low > high):
                raise ValueError(f"RobotSpec.{name}_low exceeds {name}_high somewhere: {low} > {high}")

    @property
    def control_period_s(self) -> float:
        return 1.0 / self.control_hz

    @property
    def target_size(self) -> int:
        """Entries of a command before the gripper: joints or end-effector xyz."""
        return self.dof if self.control_mode == "joint_position" else EE_DIMS

    @property
    def command_size(self) -> int:
        return self.target_size + int(self.has_gripper)

    def check_command(self, command: Any) -> np.ndarray:
        """``command`` as a float64 vector of ``command_size`` entries, or a one-line ``ValueError``
        naming the layout the robot expects."""
        array = np.asarray(command, dtype=np.float64)
        if array.shape != (self.command_size,):
            layout = "joint angles" if self.control_mode == "joint_position" else "end-effector xyz"
            gripper = " + gripper (0 closed .. 1 open)" if self.has_gripper else ""
            raise ValueError(
                f"{self.kind} expects a command of shape ({self.command_size},) = {self.target_size} "
                f"{layout}{gripper}, got shape {array.shape}"
            )
        return array


@dataclass(frozen=True, kw_only=True, eq=False)
class RobotObservation:
    """What a robot reports at ``timestamp`` (``time.monotonic()`` seconds).

    ``joint_velocities``, ``ee_position`` and ``gripper`` are ``None`` where the robot cannot know
    them. ``frames`` maps each camera of the spec to its latest uint8 frame. ``tick`` counts the
    control periods the robot has run (a gap between two observations' ticks is time that passed).
    ``info`` holds facts only a simulator knows (``success`` of its task); empty on real robots.
    """

    joint_positions: np.ndarray | None
    joint_velocities: np.ndarray | None = None
    ee_position: np.ndarray | None = None
    gripper: float | None = None
    frames: Mapping[str, np.ndarray] = field(default_factory=dict)
    timestamp: float = 0.0
    tick: int = 0
    info: Mapping[str, Any] = field(default_factory=dict)

    def current_target(self, spec: RobotSpec) -> np.ndarray | None:
        """The command that keeps the robot where it is (joint mode: the present joint angles,
        end-effector mode: the present position), gripper included; ``None`` if unknown."""
        target = self.joint_positions if spec.control_mode == "joint_position" else self.ee_position
        if target is None:
            return None
        if not spec.has_gripper:
            return np.asarray(target, dtype=np.float64).copy()
        gripper = 1.0 if self.gripper is None else self.gripper
        return np.append(np.asarray(target, dtype=np.float64), gripper)


class RobotDriver(abc.ABC):
    """One robot. ``act`` never blocks on motion; ``reset`` may take seconds (a person or the robot
    puts the scene back). ``hold`` keeps the present pose actively; ``stop`` puts the robot in its
    safe state (torque off or brakes on) and refuses commands until ``reset`` or ``connect``.
    Drivers are context managers: ``with make_robot(...) as robot:`` connects and closes."""

    @property
    @abc.abstractmethod
    def spec(self) -> RobotSpec: ...

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the link (port, simulator) and make the robot ready to take commands."""

    @abc.abstractmethod
    def observe(self) -> RobotObservation:
        """The latest state and camera frames; returns at once."""

    @abc.abstractmethod
    def act(self, command: np.ndarray) -> None:
        """Send a target (see the module docstring for its layout); returns without waiting for
        the motion. Raises :class:`RobotStoppedError` after ``stop``."""

    @abc.abstractmethod
    def reset(self) -> RobotObservation:
        """Bring the robot (and, for a simulator, the scene) to the start of an episode; blocks until
        done and returns the first observation. Re-arms a stopped robot. The observation's frames show
        the scene as the reset left it: a camera streams on through a reset, so a driver returns a frame
        captured after the reset finished, never one buffered before or during it (the previous
        episode's scene, which would start the new episode from a picture of the old one)."""

    @abc.abstractmethod
    def hold(self) -> None:
        """Keep the present pose until the next command."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Safe state now: no further motion, commands refused until ``reset``/``connect``."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop and release the link; safe to call twice."""

    def __enter__(self) -> RobotDriver:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True, kw_only=True)
class AttachedRobot:
    """A robot a driver kind can reach from this node: ``make_robot(kind, **options)`` builds its
    driver. ``name`` identifies it on the node (a port, ``sim_so101/0``)."""

    kind: str
    name: str
    options: Mapping[str, Any] = field(default_factory=dict)
    description: str = ""


@dataclass(frozen=True, kw_only=True)
class DriverKind:
    """A registered driver kind whose code lives in ``module``: ``driver`` names the
    :class:`RobotDriver` class (built with keyword options), ``attached`` a function
    ``(**config) -> list[AttachedRobot]`` that reports the robots of this kind this node reaches.
    Both are looked up on first use, so registering a kind imports nothing heavy."""

    module: str
    driver: str
    attached_robots: str

    def create(self, **options: Any) -> RobotDriver:
        return self.driver_class()(**options)

    def driver_class(self) -> type:
        return getattr(importlib.import_module(self.module), self.driver)

    def check_options(self, kind: str, options: Mapping[str, Any], where: str) -> None:
        """Raise a ``ConfigError`` naming ``where`` for an option the driver does not take, or one
        its ``check_options`` classmethod (if any) refuses, before any worker builds the robot."""
        import inspect

        from infinirl.config import ConfigError

        cls = self.driver_class()
        parameters = inspect.signature(cls.__init__).parameters
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
            known = [name for name, p in parameters.items()
                     if name != "self" and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]
            for key in options:
                if key not in known:
                    raise ConfigError(f"{where}.{key}: not an option of robot kind {kind!r}; its options: "
                                      f"{', '.join(known)}")
        check = getattr(cls, "check_options", None)
        if check is not None:
            try:
                check(**options)
            except ValueError as exc:
                raise ConfigError(f"{where}: {exc}") from None

    def attached(self, **config: Any) -> list[AttachedRobot]:
        return list(getattr(importlib.import_module(self.module), self.attached_robots)(**config))


ROBOT_DRIVERS: Registry[DriverKind] = Registry("robot driver", "infinirl.robots")

ROBOT_DRIVERS.add("sim_sawyer", DriverKind(module="infinirl.realworld.sim_sawyer", driver="SimSawyer",
                                           attached_robots="attached_sim_sawyers"))
ROBOT_DRIVERS.add("sim_so101", DriverKind(module="infinirl.realworld.sim_so101", driver="SimSO101",
                                          attached_robots="attached_sim_so101s"))
ROBOT_DRIVERS.add("so101_feetech", DriverKind(module="infinirl.realworld.so101_feetech", driver="SO101FeetechArm",
                                              attached_robots="attached_so101_arms"))


def make_robot(kind: str, **options: Any) -> RobotDriver:
    """The driver of kind ``kind`` (an unknown kind fails listing the registered ones), not yet
    connected."""
    return ROBOT_DRIVERS.get(kind).create(**options)


def discover(config: Mapping[str, Mapping[str, Any]] | None = None) -> list[AttachedRobot]:
    """Every robot this node reaches, in a stable order (by kind, then as each kind reports them).

    ``config`` maps a driver kind to its discovery options (simulated kinds: how many instances
    this node offers; serial kinds: which ports to scan). A kind not named is asked with no options,
    which reports nothing for the built-in kinds: a node offers robots only when told to. A kind
    named in ``config`` but not registered fails, listing the registered kinds.
    """
    config = dict(config or {})
    for kind in config:
        ROBOT_DRIVERS.get(kind)  # a misspelt kind fails here, with the valid ones listed
    robots: list[AttachedRobot] = []
    for kind in ROBOT_DRIVERS.names():
        robots.extend(ROBOT_DRIVERS.get(kind).attached(**config.get(kind, {})))
    return robots
