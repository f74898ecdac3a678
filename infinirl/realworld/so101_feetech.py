"""The real SO-100/SO-101 arm: six Feetech STS3215 servos (ids 1-5 the joints, 6 the gripper) on one
half-duplex serial bus (the arm's USB adapter, e.g. ``/dev/ttyACM0`` at 1 Mbaud).

``act`` is one ``SYNC_WRITE`` of the goal positions (unanswered, so it does not wait for the arm);
``observe`` one ``SYNC_READ`` of present position and speed; ``stop`` turns torque off on every
servo; ``reset`` drives to the home pose and waits until the servos report it (or fails after
``reset_timeout_s`` naming the joints that did not get there).

A servo position is 0..4095 ticks per turn; the STS firmware reports a present position below its
zero (a joint pushed past it, an offset calibration) in sign-magnitude (bit 15 the sign), so it is
decoded as such, never as a plain 16-bit number (which would read -5 as 32773).
:class:`ServoCalibration` maps it to the joint angle
(``angle = drive_sign * (ticks - homing_offset) * 2 pi / 4096``) and bounds it (``range_min`` ..
``range_max`` ticks); the gripper maps ``range_min`` (closed) .. ``range_max`` (open) to 0 .. 1. The
defaults assume an arm calibrated so that ticks 2048 is each joint's zero, as the LeRobot model's;
a JSON file (``calibration_file``) overrides them per servo.

Each servo also keeps its own position limits in EEPROM (``Min_Position_Limit`` /
``Max_Position_Limit``, which LeRobot's calibration writes from the range each joint was moved
through): the firmware refuses to go beyond them whatever goal it gets. ``connect`` reads them and
narrows every servo's range to them, so the spec's joint limits (hence the safety filter's) are
the ones the arm really has, a command is bounded before it reaches the wire instead of being cut
short by the firmware unseen, and the gripper's 0 .. 1 spans exactly its calibrated opening (its
default calibration range is the whole turn: the servo's limits decide). Limits that are inverted
or empty (``min >= max``; 0 and 0 is the firmware's multi-turn setting), beyond one turn, or clear of
the configured range refuse the connection, naming the servo. The spec before ``connect`` is the
configured one; after it, the one the limits leave.
"""

from __future__ import annotations

import glob
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from infinirl.realworld.driver import (
    AttachedRobot,
    RobotDriver,
    RobotError,
    RobotObservation,
    RobotSpec,
    RobotStoppedError,
)
from infinirl.realworld.feetech import (
    STS3215_MODEL_NUMBER,
    TICKS_PER_TURN,
    FeetechBus,
    FeetechError,
    FeetechStatusError,
    Register,
    decode_sign_magnitude,
    u16,
)
from infinirl.realworld.so101 import SO101_JOINT_HIGH, SO101_JOINT_LOW, so101_spec

__all__ = ["DEFAULT_CALIBRATION", "SO101_SERVO_IDS", "SO101FeetechArm", "ServoCalibration", "attached_so101_arms",
           "load_calibration", "within_limits"]

logger = logging.getLogger(__name__)

SO101_SERVO_IDS = (1, 2, 3, 4, 5, 6)
_RADIANS_PER_TICK = 2.0 * math.pi / TICKS_PER_TURN
_CENTER = TICKS_PER_TURN // 2


@dataclass(frozen=True, kw_only=True)
class ServoCalibration:
    """One servo: its id, the ticks at joint angle 0, the direction, and the allowed tick range (which
    ``connect`` narrows to the servo's own EEPROM position limits)."""

    id: int
    homing_offset: int = _CENTER
    drive_sign: int = 1
    range_min: int = 0
    range_max: int = TICKS_PER_TURN - 1

    def __post_init__(self) -> None:
        if self.drive_sign not in (1, -1):
            raise ValueError(f"servo {self.id}: drive_sign must be 1 or -1, got {self.drive_sign}")
        if not 0 <= self.range_min < self.range_max < TICKS_PER_TURN:
            raise ValueError(f"servo {self.id}: need 0 <= range_min < range_max < {TICKS_PER_TURN}, got "
                             f"{self.range_min}..{self.range_max}")

    def to_angle(self, ticks: int) -> float:
        return self.drive_sign * (ticks - self.homing_offset) * _RADIANS_PER_TICK

    def to_ticks(self, angle: float) -> int:
        ticks = round(self.homing_offset + self.drive_sign * angle / _RADIANS_PER_TICK)
        return min(max(ticks, self.range_min), self.range_max)

    def angle_range(self) -> tuple[float, float]:
        ends = sorted((self.to_angle(self.range_min), self.to_angle(self.range_max)))
        return ends[0], ends[1]

    def to_opening(self, ticks: int) -> float:
        """Gripper ticks -> 0 (closed, ``range_min``) .. 1 (open, ``range_max``)."""
        return min(max((ticks - self.range_min) / (self.range_max - self.range_min), 0.0), 1.0)

    def opening_to_ticks(self, opening: float) -> int:
        return round(self.range_min + min(max(opening, 0.0), 1.0) * (self.range_max - self.range_min))


def _default_calibration() -> tuple[ServoCalibration, ...]:
    joints = tuple(
        ServoCalibration(id=servo_id, range_min=_CENTER + math.ceil(low / _RADIANS_PER_TICK),
                         range_max=_CENTER + math.floor(high / _RADIANS_PER_TICK))
        for servo_id, low, high in zip(SO101_SERVO_IDS[:5], SO101_JOINT_LOW, SO101_JOINT_HIGH, strict=True)
    )
    # The whole turn: the gripper's opening is its servo's EEPROM position limits, read at connect
    # (where each gripper closes depends on how it was assembled, which only its calibration knows).
    gripper = ServoCalibration(id=SO101_SERVO_IDS[5])
    return (*joints, gripper)


DEFAULT_CALIBRATION = _default_calibration()


def load_calibration(path: str) -> tuple[ServoCalibration, ...]:
    """Six :class:`ServoCalibration` from a JSON list of objects (joints 1-5, then the gripper), each
    with the fields of :class:`ServoCalibration`; a bad file fails naming the file and the entry."""
    try:
        with open(path) as file:
            entries = json.load(file)
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"cannot read SO-101 calibration {path}: {error}") from error
    if not isinstance(entries, list) or len(entries) != len(SO101_SERVO_IDS):
        raise ValueError(f"SO-101 calibration {path} must be a list of {len(SO101_SERVO_IDS)} servo entries")
    names = {field.name for field in fields(ServoCalibration)}
    calibration = []
    for index, entry in enumerate(entries):
        unknown = sorted(set(entry) - names) if isinstance(entry, dict) else ["(not an object)"]
        if unknown:
            raise ValueError(f"SO-101 calibration {path} entry {index}: unknown keys {unknown}; keys: {sorted(names)}")
        try:
            calibration.append(ServoCalibration(**entry))
        except (TypeError, ValueError) as error:
            raise ValueError(f"SO-101 calibration {path} entry {index}: {error}") from error
    return tuple(calibration)


class SO101FeetechArm(RobotDriver):
    """The real SO-101 arm on servo bus ``port`` (see the module docstring).

    ``home`` is the pose ``reset`` drives to (a command: five angles and the gripper); ``reset_speed``
    (ticks/s) caps the servos' speed on the way there, ``reset_tolerance`` (ticks) says when a servo is
    there. ``timeout_s`` bounds each answer on the bus.
    """

    def __init__(self, *, port: str, control_hz: float = 20.0, baudrate: int = 1_000_000, timeout_s: float = 0.1,
                 calibration_file: str | None = None, home: Sequence[float] | None = None,
                 reset_speed: int = 600, reset_tolerance: int = 20, reset_timeout_s: float = 10.0) -> None:
        self.port = port
        self._baudrate = baudrate
        self._timeout_s = timeout_s
        self._control_hz = control_hz
        self.configured_calibration = load_calibration(calibration_file) if calibration_file else DEFAULT_CALIBRATION
        self.calibration = self.configured_calibration  # narrowed to the servos' own limits at connect
        self.position_limits: dict[int, tuple[int, int]] = {}  # id -> EEPROM (min, max), read at connect
        self._spec = self._spec_of(self.calibration)
        self._ids = tuple(servo.id for servo in self.calibration)
        # The spec's top joint speed as each servo's speed cap: the safety layer limits how far a
        # target moves per period, this limits how fast the servo gets there (GOAL_SPEED 0 would be
        # the servo's full speed). The gripper gets the joints' largest.
        top = [*self._spec.max_joint_velocity, float(np.max(self._spec.max_joint_velocity))]
        self._top_speed = {servo_id: u16(min(round(speed / _RADIANS_PER_TICK), 0x7FFF))
                           for servo_id, speed in zip(self._ids, top, strict=True)}
        self.home = self._spec.check_command(np.append(np.zeros(5), 1.0) if home is None else home)
        self.reset_speed = int(reset_speed)
        self.reset_tolerance = int(reset_tolerance)
        self.reset_timeout_s = float(reset_timeout_s)
        self._bus: FeetechBus | None = None
        self._stopped = False
        self._connected_at = 0.0

    @property
    def spec(self) -> RobotSpec:
        return self._spec

    def _spec_of(self, calibration: Sequence[ServoCalibration]) -> RobotSpec:
        ranges = np.array([servo.angle_range() for servo in calibration[:5]])
        return so101_spec(kind="so101_feetech", control_hz=self._control_hz, joint_low=ranges[:, 0],
                          joint_high=ranges[:, 1])

    def connect(self) -> None:
        """Open the port, check every servo answers and is an STS3215, read its EEPROM position
        limits and narrow its range to them (see the module docstring), then turn torque on with
        each goal set to where the servo already is (so nothing jumps)."""
        if self._bus is not None:
            return
        bus = FeetechBus(self.port, baudrate=self._baudrate, timeout_s=self._timeout_s)
        try:
            missing = [servo_id for servo_id in self._ids if not _answers(bus, servo_id)]
            if missing:
                raise RobotError(f"SO-101 on {self.port}: servos {missing} do not answer; check their ids, the "
                                 f"power supply and the daisy chain")
            models = bus.sync_read(Register.MODEL_NUMBER, self._ids)
            wrong = {servo_id: int.from_bytes(raw, "little") for servo_id, raw in models.items()
                     if int.from_bytes(raw, "little") != STS3215_MODEL_NUMBER}
            if wrong:
                raise RobotError(f"SO-101 on {self.port}: servos {wrong} (id: model number) are not STS3215 "
                                 f"({STS3215_MODEL_NUMBER})")
            # Both limits in one read: Min_Position_Limit (9, 2 bytes) then Max_Position_Limit (11, 2 bytes).
            raw = bus.sync_read((Register.MIN_POSITION_LIMIT[0], 4), self._ids)
            limits = {servo_id: (int.from_bytes(data[:2], "little"), int.from_bytes(data[2:], "little"))
                      for servo_id, data in raw.items()}
            calibration = within_limits(self.configured_calibration, limits, self.port)
        except BaseException:
            bus.close()
            raise
        self.position_limits = limits
        self.calibration = calibration
        self._spec = self._spec_of(calibration)
        self._warn_about_limits()
        self._bus = bus
        self._connected_at = time.monotonic()
        self._arm_at_present_pose()

    def observe(self) -> RobotObservation:
        """The present pose; a servo reporting status error bits (overload, overheat, ...) is named
        in ``info["servo_errors"]`` (id -> bits), its reading kept: the safety layer decides."""
        bus = self._require_bus()
        raw, errors = bus.sync_read_status((Register.PRESENT_POSITION[0], 4), self._ids)  # position then speed
        ticks = {servo_id: decode_sign_magnitude(data[:2]) for servo_id, data in raw.items()}
        speeds = {servo_id: decode_sign_magnitude(data[2:]) for servo_id, data in raw.items()}
        joints = self.calibration[:5]
        now = time.monotonic()
        return RobotObservation(
            joint_positions=np.array([servo.to_angle(ticks[servo.id]) for servo in joints]),
            joint_velocities=np.array([servo.drive_sign * speeds[servo.id] * _RADIANS_PER_TICK for servo in joints]),
            gripper=self.calibration[5].to_opening(ticks[self.calibration[5].id]),
            timestamp=now,
            tick=int((now - self._connected_at) * self._spec.control_hz),
            info={"servo_errors": errors} if errors else {},
        )

    def act(self, command: np.ndarray) -> None:
        command = self._spec.check_command(command)
        bus = self._require_bus()
        if self._stopped:
            raise RobotStoppedError(f"SO-101 on {self.port} is stopped (torque off); reset() re-arms it")
        bus.sync_write(Register.GOAL_POSITION, self.goal_ticks(command))

    def goal_ticks(self, command: np.ndarray) -> dict[int, bytes]:
        """A command -> each servo's goal position register value (clipped to its calibrated range)."""
        goals = {servo.id: u16(servo.to_ticks(angle)) for servo, angle in zip(self.calibration[:5], command[:5],
                                                                               strict=True)}
        gripper = self.calibration[5]
        goals[gripper.id] = u16(gripper.opening_to_ticks(float(command[5])))
        return goals

    def reset(self) -> RobotObservation:
        """Torque on (re-arms a stopped arm), drive to ``home`` at ``reset_speed``, wait until there."""
        bus = self._require_bus()
        self._arm_at_present_pose()
        bus.sync_write(Register.GOAL_SPEED, {servo_id: u16(self.reset_speed) for servo_id in self._ids})
        goals = self.goal_ticks(self.home)
        bus.sync_write(Register.GOAL_POSITION, goals)
        deadline = time.monotonic() + self.reset_timeout_s
        try:
            while True:
                present = self._present_ticks(bus)
                away = [servo_id for servo_id in self._ids if abs(present[servo_id]
                                                                 - int.from_bytes(goals[servo_id], "little"))
                        > self.reset_tolerance]
                if not away:
                    break
                if time.monotonic() > deadline:
                    raise RobotError(f"SO-101 on {self.port}: servos {away} did not reach the home pose within "
                                     f"{self.reset_timeout_s} s (blocked, or reset_speed too low)")
                time.sleep(self._spec.control_period_s)
        finally:
            bus.sync_write(Register.GOAL_SPEED, self._top_speed)
        return self.observe()

    def hold(self) -> None:
        """Goal := present position, so the arm stays where it is."""
        bus = self._require_bus()
        bus.sync_write(Register.GOAL_POSITION, self._hold_goals(bus))

    def stop(self) -> None:
        """Torque off on every servo (the arm goes limp: it cannot move itself)."""
        bus = self._require_bus()
        self._stopped = True
        bus.sync_write(Register.TORQUE_ENABLE, {servo_id: b"\x00" for servo_id in self._ids})

    def close(self) -> None:
        """Torque off, then release the port (as LeRobot does on disconnect)."""
        if self._bus is None:
            return
        try:
            self.stop()
        finally:
            self._bus.close()
            self._bus = None

    def _warn_about_limits(self) -> None:
        gripper = self.calibration[5]
        if self.position_limits[gripper.id] == (0, TICKS_PER_TURN - 1):
            logger.warning("SO-101 on %s: gripper servo %d has the factory position limits 0..%d, so its 0 .. 1 "
                           "spans a whole turn; calibrate the arm (e.g. lerobot-calibrate) to store its opening",
                           self.port, gripper.id, TICKS_PER_TURN - 1)
        for servo, configured, angle in zip(self.calibration[:5], self.configured_calibration[:5], self.home[:5],
                                            strict=True):
            if (servo.range_min, servo.range_max) != (configured.range_min, configured.range_max):
                logger.info("SO-101 on %s: servo %d's EEPROM limits narrow its range to %d..%d ticks", self.port,
                            servo.id, servo.range_min, servo.range_max)
            low, high = servo.angle_range()
            if not low <= angle <= high:
                logger.warning("SO-101 on %s: the home angle %.4g of servo %d is outside its limits %.4g..%.4g rad; "
                               "reset drives it to the nearest", self.port, angle, servo.id, low, high)

    def _arm_at_present_pose(self) -> None:
        bus = self._require_bus()
        bus.sync_write(Register.GOAL_POSITION, self._hold_goals(bus))
        bus.sync_write(Register.GOAL_SPEED, self._top_speed)
        bus.sync_write(Register.TORQUE_ENABLE, {servo_id: b"\x01" for servo_id in self._ids})
        self._stopped = False

    def _present_ticks(self, bus: FeetechBus) -> dict[int, int]:
        raw = bus.sync_read(Register.PRESENT_POSITION, self._ids)
        return {servo_id: decode_sign_magnitude(data) for servo_id, data in raw.items()}

    def _hold_goals(self, bus: FeetechBus) -> dict[int, bytes]:
        """Goal registers that keep each servo where it is: its present position, brought into the
        goal register's 0..4095 (a joint read below its zero holds at 0, the nearest goal there is)."""
        return {servo_id: u16(min(max(ticks, 0), TICKS_PER_TURN - 1))
                for servo_id, ticks in self._present_ticks(bus).items()}

    def _require_bus(self) -> FeetechBus:
        if self._bus is None:
            raise RobotError(f"SO-101 on {self.port} is not connected: call connect() first")
        return self._bus


def within_limits(calibration: Sequence[ServoCalibration], limits: dict[int, tuple[int, int]],
                  port: str) -> tuple[ServoCalibration, ...]:
    """``calibration`` with each servo's range narrowed to its EEPROM position limits ``limits``
    (id -> (min, max) ticks); a one-line :class:`RobotError` naming every servo whose limits are
    inverted or empty, beyond one turn, or clear of its configured range."""
    narrowed, problems = [], []
    for servo in calibration:
        low, high = limits[servo.id]
        if low >= high:
            problems.append(f"servo {servo.id} has Min_Position_Limit {low} >= Max_Position_Limit {high} (inverted, "
                            f"or 0 and 0: the multi-turn setting)")
        elif high >= TICKS_PER_TURN:
            problems.append(f"servo {servo.id} has Max_Position_Limit {high}, beyond one turn "
                            f"(0..{TICKS_PER_TURN - 1})")
        elif max(low, servo.range_min) >= min(high, servo.range_max):
            problems.append(f"servo {servo.id}'s limits {low}..{high} leave nothing of its calibrated range "
                            f"{servo.range_min}..{servo.range_max}")
        else:
            narrowed.append(replace(servo, range_min=max(low, servo.range_min), range_max=min(high, servo.range_max)))
    if problems:
        raise RobotError(f"SO-101 on {port}: {'; '.join(problems)}; recalibrate the arm (e.g. lerobot-calibrate) or "
                         "fix calibration_file")
    return tuple(narrowed)


#: Pings a servo gets at connect before it counts as missing: a bus drops an answer now and then
#: (noise on the line, a busy host reading the port late), which must not refuse a whole arm.
CONNECT_PING_ATTEMPTS = 3


def _answers(bus: FeetechBus, servo_id: int, attempts: int = CONNECT_PING_ATTEMPTS) -> bool:
    for _ in range(attempts):
        try:
            bus.ping(servo_id)
        except FeetechStatusError:
            return True  # it answered: a fault it reports is the safety layer's to act on, not a missing servo
        except FeetechError:
            continue
        return True
    return False


def attached_so101_arms(*, ports: Sequence[str] = (), baudrate: int = 1_000_000, timeout_s: float = 0.05,
                        **options: Any) -> list[AttachedRobot]:
    """SO-101 arms on the configured ``ports`` (paths or globs such as ``/dev/ttyACM*``): a port is an
    arm when all six servos answer a ping. A port that cannot be opened, or with some servos missing, is
    reported in the log and left out; no port is scanned unless configured."""
    arms = []
    for pattern in ports:
        for path in sorted(glob.glob(pattern)) or [pattern]:
            try:
                bus = FeetechBus(path, baudrate=baudrate, timeout_s=timeout_s)
            except FeetechError as error:
                logger.warning("SO-101 discovery: %s", error)
                continue
            try:
                missing = [servo_id for servo_id in SO101_SERVO_IDS if not _answers(bus, servo_id)]
            finally:
                bus.close()
            if missing:
                logger.warning("SO-101 discovery: %s has no servos %s; not an SO-101 arm, or one not powered",
                               path, missing)
                continue
            arms.append(AttachedRobot(kind="so101_feetech", name=path,
                                      options={**options, "port": path, "baudrate": baudrate},
                                      description="SO-101 arm (Feetech STS3215 bus)"))
    return arms
