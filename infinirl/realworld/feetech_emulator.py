"""An emulator of a Feetech STS3215 servo bus on a pseudo-terminal: the real driver, unchanged,
talks to it through ``emulator.path`` as it would to ``/dev/ttyACM0``.

A thread serves the pty's other end like ``ids`` servos on one bus: each has the STS3215 control
table (model number, the EEPROM position limits, torque enable, goal position and speed, present
position and speed), and a servo whose torque is on moves its present position toward its goal at
its speed (``max_speed`` ticks/s, or the lower goal speed if one is set) in wall-clock time. The
position limits (``Min_Position_Limit`` / ``Max_Position_Limit``, addresses 9 and 11) are the
factory's 0 and 4095 unless ``limits`` gives a servo its calibrated ones; as the firmware does, a
goal beyond them is taken as the nearest limit (both 0: no limits, the multi-turn setting). A
request with a wrong checksum is ignored, as a servo ignores it; a request to an id not on the bus
gets no answer. Present position is sign-magnitude (bit 15 the sign), as STS firmware reports a
joint pushed below the encoder's zero (:meth:`push`). Faults for tests: :meth:`corrupt_replies`
sends answers with a broken checksum, :meth:`drop_replies` loses answers on the wire,
:meth:`set_status_error` sets status error bits (e.g. overload) in a servo's answers, :meth:`unplug`
takes a servo off the bus, :meth:`set_max_speed` slows a joint (a load), :meth:`block` puts an
obstacle in a joint's way (contact, a hand holding it: the servo keeps its goal and pushes,
reporting speed 0; the overload protection a long stall trips on a real servo is
:meth:`set_status_error`'s to inject). Every request is kept, byte for byte, in :attr:`requests`.
"""

from __future__ import annotations

import math
import os
import select
import threading
import time
import tty
from collections.abc import Iterable, Mapping

from infinirl.realworld.feetech import (
    BROADCAST_ID,
    HEADER,
    STS3215_MODEL_NUMBER,
    Instruction,
    Register,
    checksum,
    decode_sign_magnitude,
    encode_sign_magnitude,
    u16,
)

__all__ = ["EmulatedServo", "FeetechBusEmulator"]

_CENTER = 2048


class EmulatedServo:
    """One STS3215's control table and motion."""

    def __init__(self, servo_id: int, position: int, max_speed: float, limits: tuple[int, int] = (0, 4095)) -> None:
        self.table = bytearray(256)
        self.max_speed = float(max_speed)
        self._write(Register.MODEL_NUMBER, u16(STS3215_MODEL_NUMBER))
        self._write(Register.ID, bytes([servo_id]))
        self._write(Register.MIN_POSITION_LIMIT, u16(limits[0]))
        self._write(Register.MAX_POSITION_LIMIT, u16(limits[1]))
        self._write(Register.GOAL_POSITION, u16(min(max(position, 0), 4095)))
        self._write(Register.PRESENT_POSITION, encode_sign_magnitude(position))
        self._position = float(position)
        self.status_error = 0  # the error byte of this servo's answers
        self.free = (-math.inf, math.inf)  # the span an obstacle leaves the joint (see block)

    def _write(self, register: tuple[int, int], data: bytes) -> None:
        self.table[register[0]:register[0] + len(data)] = data

    def value(self, register: tuple[int, int]) -> int:
        address, size = register
        return int.from_bytes(self.table[address:address + size], "little")

    @property
    def torque_enabled(self) -> bool:
        return bool(self.value(Register.TORQUE_ENABLE))

    def advance(self, seconds: float) -> None:
        """``seconds`` of motion toward the goal (none with torque off)."""
        goal = self.value(Register.GOAL_POSITION)
        low, high = self.value(Register.MIN_POSITION_LIMIT), self.value(Register.MAX_POSITION_LIMIT)
        if low or high:  # both 0 is the firmware's "no limits"
            goal = min(max(goal, low), high)
        speed = self.max_speed
        if self.value(Register.GOAL_SPEED):
            speed = min(speed, self.value(Register.GOAL_SPEED))
        moving = self.torque_enabled and abs(goal - self._position) > 0.5
        velocity = 0.0
        if moving and seconds > 0:
            direction = 1.0 if goal > self._position else -1.0
            step = min(abs(goal - self._position), speed * seconds)
            reached = min(max(self._position + direction * step, self.free[0]), self.free[1])
            velocity = (reached - self._position) / seconds
            self._position = reached
        self._write(Register.PRESENT_POSITION, encode_sign_magnitude(round(self._position)))
        self._write(Register.PRESENT_SPEED, encode_sign_magnitude(max(min(round(velocity), 0x7FFF), -0x7FFF)))
        self._write(Register.MOVING, bytes([int(moving)]))

    def write(self, address: int, data: bytes) -> None:
        self.table[address:address + len(data)] = data

    def push(self, position: int) -> None:
        """Move the joint to ``position`` ticks from outside (a hand, a collision)."""
        self._position = float(position)
        self._write(Register.PRESENT_POSITION, encode_sign_magnitude(position))

    def block(self, at: float | None) -> None:
        """An obstacle at ``at`` ticks the joint cannot move past from the side it is on (``None``:
        the joint held where it is, both ways)."""
        if at is None or at == self._position:
            self.free = (self._position, self._position)
        elif at > self._position:
            self.free = (-math.inf, float(at))
        else:
            self.free = (float(at), math.inf)


class FeetechBusEmulator:
    """``ids`` emulated servos behind a pty (see the module docstring); a context manager."""

    def __init__(self, ids: Iterable[int] = range(1, 7), *, positions: Mapping[int, int] | None = None,
                 max_speed: float = 3000.0, limits: Mapping[int, tuple[int, int]] | None = None) -> None:
        positions, limits = dict(positions or {}), dict(limits or {})
        self.servos = {servo_id: EmulatedServo(servo_id, positions.get(servo_id, _CENTER), max_speed,
                                               limits.get(servo_id, (0, 4095)))
                       for servo_id in ids}
        self.requests: list[bytes] = []
        self.ignored_requests = 0  # requests dropped for a wrong checksum
        self._unplugged: set[int] = set()
        self._corrupt = 0
        self._drop = 0
        self._lock = threading.Lock()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes pass through unchanged
        self.path = os.ttyname(self._slave)
        self._closing = False
        self._last_advance = time.monotonic()
        self._thread = threading.Thread(target=self._serve, name="feetech-emulator", daemon=True)
        self._thread.start()

    def __enter__(self) -> FeetechBusEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._closing = True
        self._thread.join(5.0)
        os.close(self._master)
        os.close(self._slave)

    def corrupt_replies(self, count: int) -> None:
        """The next ``count`` answers go out with a wrong checksum."""
        with self._lock:
            self._corrupt = count

    def drop_replies(self, count: int) -> None:
        """The next ``count`` answers are lost on the wire (the driver times out waiting)."""
        with self._lock:
            self._drop = count

    def set_status_error(self, servo_id: int, error: int) -> None:
        """Servo ``servo_id`` answers with status error byte ``error`` (bit 5: overload) until set to 0;
        its data is sent as usual, as a real servo's."""
        with self._lock:
            self.servos[servo_id].status_error = error

    def push(self, servo_id: int, position: int) -> None:
        """Servo ``servo_id``'s joint is moved to ``position`` ticks from outside (may be below 0)."""
        with self._lock:
            self._advance()
            self.servos[servo_id].push(position)

    def block(self, servo_id: int, at: int | None = None) -> None:
        """An obstacle in servo ``servo_id``'s way at ``at`` ticks (default: the joint held where it
        is); the servo pushes toward its goal without getting past it, until :meth:`unblock`."""
        with self._lock:
            self._advance()
            self.servos[servo_id].block(at)

    def unblock(self, servo_id: int) -> None:
        """The obstacle clears: the joint moves on toward its goal."""
        with self._lock:
            self._advance()
            self.servos[servo_id].free = (-math.inf, math.inf)

    def set_max_speed(self, servo_id: int, ticks_per_s: float) -> None:
        """Servo ``servo_id`` moves at most this fast (a loaded joint is slower than a free one)."""
        with self._lock:
            self._advance()
            self.servos[servo_id].max_speed = float(ticks_per_s)

    def unplug(self, servo_id: int) -> None:
        """Servo ``servo_id`` stops answering (its packets are still on the wire, unheard)."""
        with self._lock:
            self._unplugged.add(servo_id)

    def position(self, servo_id: int) -> int:
        with self._lock:
            self._advance()
            address, size = Register.PRESENT_POSITION
            return decode_sign_magnitude(bytes(self.servos[servo_id].table[address:address + size]))

    def register(self, servo_id: int, register: tuple[int, int]) -> int:
        with self._lock:
            self._advance()
            return self.servos[servo_id].value(register)

    # ---- serving ---------------------------------------------------------------------------------

    def _serve(self) -> None:
        buffer = bytearray()
        while not self._closing:
            readable, _, _ = select.select([self._master], [], [], 0.02)
            if not readable:
                continue
            try:
                buffer += os.read(self._master, 4096)
            except OSError:  # the driver side was closed and reopened: keep serving
                continue
            while (packet := _take_packet(buffer)) is not None:
                with self._lock:
                    self._advance()
                    replies = self._handle(packet)
                for reply in replies:
                    if reply:
                        os.write(self._master, reply)

    def _advance(self) -> None:
        now = time.monotonic()
        for servo in self.servos.values():
            servo.advance(now - self._last_advance)
        self._last_advance = now

    def _handle(self, packet: bytes) -> list[bytes]:
        self.requests.append(packet)
        body, received = packet[2:-1], packet[-1]
        if checksum(body) != received:
            self.ignored_requests += 1
            return []
        servo_id, instruction, params = body[0], body[2], body[3:]
        if instruction == Instruction.SYNC_WRITE and servo_id == BROADCAST_ID:
            address, size = params[0], params[1]
            for start in range(2, len(params), size + 1):
                self._servo_write(params[start], address, params[start + 1:start + 1 + size])
            return []
        if instruction == Instruction.SYNC_READ and servo_id == BROADCAST_ID:
            address, size = params[0], params[1]
            return [self._reply(target, self._read(target, address, size)) for target in params[2:]
                    if self._present(target)]
        if not self._present(servo_id):
            return []
        if instruction == Instruction.PING:
            return [self._reply(servo_id, b"")]
        if instruction == Instruction.READ:
            return [self._reply(servo_id, self._read(servo_id, params[0], params[1]))]
        if instruction == Instruction.WRITE:
            self._servo_write(servo_id, params[0], params[1:])
            return [self._reply(servo_id, b"")]
        return []

    def _present(self, servo_id: int) -> bool:
        return servo_id in self.servos and servo_id not in self._unplugged

    def _read(self, servo_id: int, address: int, size: int) -> bytes:
        return bytes(self.servos[servo_id].table[address:address + size])

    def _servo_write(self, servo_id: int, address: int, data: bytes) -> None:
        if self._present(servo_id):
            self.servos[servo_id].write(address, bytes(data))

    def _reply(self, servo_id: int, params: bytes) -> bytes:
        if self._drop:
            self._drop -= 1
            return b""
        body = bytes([servo_id, len(params) + 2, self.servos[servo_id].status_error]) + params
        check = checksum(body)
        if self._corrupt:
            self._corrupt -= 1
            check ^= 0xFF
        return HEADER + body + bytes([check])


def _take_packet(buffer: bytearray) -> bytes | None:
    """Remove and return the first complete packet in ``buffer`` (bytes before a header dropped)."""
    start = buffer.find(HEADER)
    if start < 0:
        del buffer[:max(0, len(buffer) - 1)]
        return None
    del buffer[:start]
    if len(buffer) < 4:
        return None
    end = 4 + buffer[3]
    if len(buffer) < end:
        return None
    packet = bytes(buffer[:end])
    del buffer[:end]
    return packet
