"""The safety layer every command passes before it reaches a robot driver.

:class:`SafetyFilter` (a pure function of the command, the last target and the spec) clips

* non-finite entries: replaced by the last target's value (a NaN from a diverged policy must not
  reach a servo);
* position limits: joint angles to the spec's joint limits (``joint_position`` robots), the
  end-effector target to the workspace box (``ee_position`` robots), the gripper to 0 .. 1;
* velocity: each joint (or the end effector) moves at most ``velocity_scale`` times the spec's
  top speed per control period from the last target;
* tracking: each joint (or the end effector) target leads the *measured* pose by at most what the
  spec's top speed covers in ``max_lead_s``. The velocity bound alone is relative to the last
  target: a joint that is blocked (contact, load) or lags would let the target walk away from the
  real pose step after step, and the arm would jump the whole gap when the obstacle clears. The
  lead bound is a window around the measured pose, not a step from it, so the steady lag of a
  joint that follows a moving target (a period or two of motion) and a loaded servo's steady
  position error stay inside it and the arm still gets everywhere. The gripper is exempt: a
  grasp is a closed target the fingers press toward while the object holds them open.

The position limits are applied once more after these, so a command is within them even from a
pose beyond them (the limit wins there).

Each clipped entry is a :class:`ClipRecord`, logged as a warning and counted. The last target (or
the reported pose it starts from) and the measured pose are not trusted either: when one is not
finite the filter raises :class:`UnknownPoseError`, and :class:`SafeRobot` holds the driver, records
an ``unknown_pose`` event, sends nothing and raises it to the caller; the next command re-reads the
pose.

The measured pose :class:`SafeRobot` bounds a command with is the latest observation made through it
since the previous command (the control loop observes once per step, after the command's period),
or, when there is none, one it reads itself: no command is bounded by a pose older than the command
before it.

:class:`SafeRobot` wraps a driver with the filter and a monitor thread:

* **watchdog**: no command for ``command_deadline_s`` -> ``hold()`` (the commander stalled; the
  robot must not keep following a stale target). The next command resumes;
* **heartbeat**: the pipeline calls :meth:`SafeRobot.heartbeat` while it is alive (the learner's
  or the link's progress); none for ``heartbeat_deadline_s`` -> ``stop()``, and commands are
  refused until ``reset()``. A stall this long is a failure, not a pause.

Both deadlines restart when ``connect`` or ``reset`` returns (a reset may take as long as it needs).
A control loop that idles between episodes on purpose keeps giving the heartbeat (the robot held).

A driver may report hardware faults in ``observation.info["servo_errors"]`` (servo -> the status
bits it set, e.g. overload): :meth:`SafeRobot.observe` then holds the robot, records a
``servo_error`` event and raises :class:`ServoFaultError` (the episode ends; the next reset re-arms).

:meth:`SafeRobot.act` returns the command it sent (the filtered one): whoever tracks the robot's
target must track that, not what it asked for.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np

from infinirl.realworld.driver import RobotDriver, RobotError, RobotObservation, RobotSpec, RobotStoppedError

__all__ = ["ClipRecord", "SafeRobot", "SafetyConfig", "SafetyEvent", "SafetyFilter", "ServoFaultError",
           "UnknownPoseError"]

logger = logging.getLogger(__name__)


class UnknownPoseError(RobotError):
    """The pose motion would be limited from (the last target, or the robot's reported pose) is not
    finite: no command is safe to send until the robot reports a finite one."""


class ServoFaultError(RobotError):
    """A servo reported a hardware fault (overload, overheat, ...): the robot was held."""


@dataclass(frozen=True, kw_only=True)
class SafetyConfig:
    """Safety defaults: half the robot's top speed, a target at most 0.1 s of top-speed motion ahead
    of the measured pose, hold after 0.5 s without a command, stop after 2 s without a heartbeat.
    ``None`` turns that check off.

    ``max_lead_s`` is a time so that one value fits robots of any speed and rate: 0.1 s is 0.3 rad
    on the SO-101 (3 rad/s), four control periods of half-speed motion at 20 Hz, where a joint
    following a moving target lags by one or two and a loaded STS3215 sags by a few degrees."""

    velocity_scale: float = 0.5
    max_lead_s: float | None = 0.1
    command_deadline_s: float | None = 0.5
    heartbeat_deadline_s: float | None = 2.0

    def __post_init__(self) -> None:
        if not 0 < self.velocity_scale <= 1:
            raise ValueError(f"SafetyConfig.velocity_scale must be in (0, 1], got {self.velocity_scale}")
        for name in ("max_lead_s", "command_deadline_s", "heartbeat_deadline_s"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ValueError(f"SafetyConfig.{name} must be positive or None, got {value}")


@dataclass(frozen=True, kw_only=True)
class ClipRecord:
    """One command entry the filter changed: ``kind`` is ``non_finite``, ``joint_limit``,
    ``workspace``, ``gripper``, ``velocity`` or ``tracking`` (too far ahead of the measured pose)."""

    kind: str
    index: int
    requested: float
    allowed: float


@dataclass(frozen=True, kw_only=True)
class SafetyEvent:
    """``watchdog_hold``, ``heartbeat_stop``, ``unknown_pose`` or ``servo_error``, at ``time``
    (``time.monotonic()``)."""

    kind: str
    time: float
    detail: str


class SafetyFilter:
    """Clips commands for one robot (see the module docstring); keeps no state between calls."""

    def __init__(self, spec: RobotSpec, config: SafetyConfig | None = None) -> None:
        self.spec = spec
        self.config = config or SafetyConfig()
        size = spec.target_size
        if spec.control_mode == "joint_position":
            self._low, self._high, self._limit_kind = spec.joint_low, spec.joint_high, "joint_limit"
            top_speed = spec.max_joint_velocity
        else:
            self._low, self._high, self._limit_kind = spec.workspace_low, spec.workspace_high, "workspace"
            top_speed = np.full(size, spec.max_ee_speed)
        self._max_step = top_speed * self.config.velocity_scale * spec.control_period_s
        self._max_lead = None if self.config.max_lead_s is None else top_speed * self.config.max_lead_s

    def __call__(self, command: np.ndarray, reference: np.ndarray,
                 measured: np.ndarray | None = None) -> tuple[np.ndarray, list[ClipRecord]]:
        """``command`` made safe to send after ``reference`` (the last target sent, or the present
        pose) with the robot at ``measured`` (a command that would hold it where it was observed:
        :meth:`RobotObservation.current_target`), and a record of each entry changed. Without
        ``measured`` the tracking bound is not applied. Raises :class:`UnknownPoseError` when
        ``reference`` or ``measured`` is not finite: motion cannot be limited from an unknown pose,
        and a non-finite command entry would be replaced by it."""
        requested = self.spec.check_command(command)
        reference = self.spec.check_command(reference)
        unknown = np.flatnonzero(~np.isfinite(reference))
        if unknown.size:
            raise UnknownPoseError(f"{self.spec.kind}: the pose to limit motion from is not finite at entries "
                                   f"{unknown.tolist()} ({reference.tolist()}); nothing is sent")
        size = self.spec.target_size
        if measured is not None:
            measured = self.spec.check_command(measured)
            unknown = np.flatnonzero(~np.isfinite(measured[:size]))  # the gripper's reading bounds nothing
            if unknown.size:
                raise UnknownPoseError(f"{self.spec.kind}: the measured pose is not finite at entries "
                                       f"{unknown.tolist()} ({measured.tolist()}); nothing is sent")
        safe = requested.copy()
        records: list[ClipRecord] = []
        bad = ~np.isfinite(safe)
        safe[bad] = reference[bad]
        records += [ClipRecord(kind="non_finite", index=int(i), requested=float(requested[i]),
                               allowed=float(safe[i])) for i in np.flatnonzero(bad)]
        self._clip(safe, slice(0, size), self._low, self._high, self._limit_kind, records)
        if self.spec.has_gripper:
            self._clip(safe, slice(size, size + 1), np.zeros(1), np.ones(1), "gripper", records)
        low = reference[:size] - self._max_step
        high = reference[:size] + self._max_step
        self._clip(safe, slice(0, size), low, high, "velocity", records)
        if measured is not None and self._max_lead is not None:
            # After the velocity bound, so it wins: when the last target is already further ahead than
            # this (the joint was blocked, or pushed back by hand), the target comes back toward the
            # real pose, which moves the arm less, never more.
            low = measured[:size] - self._max_lead
            high = measured[:size] + self._max_lead
            self._clip(safe, slice(0, size), low, high, "tracking", records)
        # The limits again, last: from a pose beyond them (a robot pushed there, a sensor's offset) the
        # velocity and tracking windows lie outside them too, and the limits win over both.
        self._clip(safe, slice(0, size), self._low, self._high, self._limit_kind, records)
        return safe, records

    @staticmethod
    def _clip(values: np.ndarray, part: slice, low: np.ndarray, high: np.ndarray, kind: str,
              records: list[ClipRecord]) -> None:
        before = values[part].copy()
        values[part] = np.clip(before, low, high)
        for offset in np.flatnonzero(values[part] != before):
            records.append(ClipRecord(kind=kind, index=part.start + int(offset), requested=float(before[offset]),
                                      allowed=float(values[part][offset])))


class SafeRobot(RobotDriver):
    """``driver`` behind a :class:`SafetyFilter`, a command watchdog and a heartbeat monitor.

    ``clip_counts`` / ``event_counts`` count clips and events by kind; ``clips`` / ``events`` keep
    the latest ``history`` of each.
    """

    def __init__(self, driver: RobotDriver, config: SafetyConfig | None = None, *, history: int = 1000) -> None:
        self.driver = driver
        self.config = config or SafetyConfig()
        self.filter = SafetyFilter(driver.spec, self.config)
        self.clip_counts: Counter[str] = Counter()
        self.event_counts: Counter[str] = Counter()
        self.clips: deque[ClipRecord] = deque(maxlen=history)
        self.events: deque[SafetyEvent] = deque(maxlen=history)
        self._lock = threading.RLock()
        self._reference: np.ndarray | None = None
        self._measured: np.ndarray | None = None  # the pose observed since the last command (see the module doc)
        self._last_command = self._last_heartbeat = time.monotonic()
        self._holding = self._stopped = self._stop_confirmed = self._busy = False
        self._closing = threading.Event()
        self._monitor: threading.Thread | None = None

    @property
    def spec(self) -> RobotSpec:
        return self.driver.spec

    def connect(self) -> None:
        self.driver.connect()
        # A driver may learn its limits only from the robot (the SO-101 reads its servos' EEPROM
        # position limits), so the filter is built again from the spec it has once connected.
        self.filter = SafetyFilter(self.driver.spec, self.config)
        self._rearm(self.driver.observe())
        if self._monitor is None and (self.config.command_deadline_s or self.config.heartbeat_deadline_s):
            self._closing.clear()
            self._monitor = threading.Thread(target=self._watch, name=f"{self.spec.kind}-safety", daemon=True)
            self._monitor.start()

    def observe(self) -> RobotObservation:
        # Under the lock: the monitor thread's hold/stop talk to the same driver (one serial bus).
        with self._lock:
            observation = self.driver.observe()
            self._measured = self._pose_of(observation)
            faults = observation.info.get("servo_errors")
            if faults:
                detail = "; ".join(f"servo {servo}: {', '.join(bits)}" for servo, bits in faults.items())
                self._event("servo_error", detail)
                self.hold()
                raise ServoFaultError(f"{self.spec.kind} reports a fault ({detail}); held")
            return observation

    def act(self, command: np.ndarray) -> np.ndarray:
        """Send ``command`` through the filter; returns what was sent."""
        with self._lock:
            if self._stopped:
                raise RobotStoppedError(f"{self.spec.kind} was stopped by the safety layer; reset() re-arms it")
            measured = self._measured
            if measured is None or self._reference is None:
                measured = self._pose_of(self.driver.observe())
                if self._reference is None:
                    self._reference = measured
            try:
                safe, records = self.filter(command, self._reference, measured)
            except UnknownPoseError as exc:
                # The driver's own hold keeps the pose without a target from us; the next command
                # re-reads the pose, so a reading that recovers resumes.
                self._event("unknown_pose", str(exc))
                self._reference = self._measured = None
                self.driver.hold()
                self._holding = True
                raise
            for record in records:
                self.clips.append(record)
                self.clip_counts[record.kind] += 1
                logger.warning("%s command clipped (%s): entry %d %.6g -> %.6g", self.spec.kind, record.kind,
                               record.index, record.requested, record.allowed)
            self.driver.act(safe)
            self._reference = safe
            self._measured = None  # the next command needs a pose observed after this one
            self._last_command = time.monotonic()
            self._holding = False
            return safe.copy()

    def heartbeat(self) -> None:
        """The pipeline is alive; call it at least every ``heartbeat_deadline_s``."""
        self._last_heartbeat = time.monotonic()

    def reset(self) -> RobotObservation:
        with self._lock:
            self._busy = True
        try:
            observation = self.driver.reset()
        finally:
            with self._lock:
                self._busy = False
        self._rearm(observation)
        return observation

    def hold(self) -> None:
        with self._lock:
            self.driver.hold()
            self._holding = True
            self._reference = self._measured = None  # the next command is limited from where the robot stopped

    def stop(self) -> None:
        with self._lock:
            self._stopped = True  # commands refused from now on, even if the driver's stop fails
            self.driver.stop()
            self._stop_confirmed = True

    def close(self) -> None:
        self._closing.set()
        if self._monitor is not None:
            self._monitor.join(5.0)
            self._monitor = None
        self.driver.close()

    def _pose_of(self, observation: RobotObservation) -> np.ndarray:
        """The observation's pose as a command; NaN where the robot does not report it, so the
        filter refuses to bound a command with it (:class:`UnknownPoseError`)."""
        pose = observation.current_target(self.spec)
        return np.full(self.spec.command_size, np.nan) if pose is None else pose

    def _rearm(self, observation: RobotObservation) -> None:
        with self._lock:
            self._reference = observation.current_target(self.spec)
            self._measured = self._pose_of(observation)
            self._last_command = self._last_heartbeat = time.monotonic()
            self._holding = self._stopped = self._stop_confirmed = False

    def _event(self, kind: str, detail: str) -> None:
        self.events.append(SafetyEvent(kind=kind, time=time.monotonic(), detail=detail))
        self.event_counts[kind] += 1
        logger.warning("%s safety: %s (%s)", self.spec.kind, kind, detail)

    def _watch(self) -> None:
        deadlines = [d for d in (self.config.command_deadline_s, self.config.heartbeat_deadline_s) if d]
        interval = min(deadlines) / 5
        while not self._closing.wait(interval):
            with self._lock:
                if self._busy or self._stop_confirmed:  # a stop that failed is tried again
                    continue
                now = time.monotonic()
                heartbeat_age = now - self._last_heartbeat
                command_age = now - self._last_command
                try:
                    if self._stopped or (self.config.heartbeat_deadline_s
                                         and heartbeat_age > self.config.heartbeat_deadline_s):
                        self._event("heartbeat_stop", f"no heartbeat for {heartbeat_age:.3f} s")
                        self.stop()
                    elif (self.config.command_deadline_s and not self._holding
                          and command_age > self.config.command_deadline_s):
                        self._event("watchdog_hold", f"no command for {command_age:.3f} s")
                        self.hold()
                except Exception:  # a failed hold/stop is logged and retried at the next check
                    logger.exception("%s safety: hold/stop failed", self.spec.kind)
