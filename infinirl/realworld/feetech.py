"""The Feetech serial bus servo protocol (SCS/STS series, e.g. the STS3215 of the SO-100/SO-101 arm),
spoken over a plain POSIX tty: no vendor SDK, no pyserial.

Every packet is ``0xFF 0xFF id length instruction params... checksum`` with ``length = len(params) + 2``
and ``checksum = ~(id + length + instruction + sum(params)) & 0xFF``. A servo answers with a status
packet ``0xFF 0xFF id length error params... checksum`` (``error`` is a bit field, 0 when all is
well). The bus is half duplex: one request, then its replies, then the next request. Multi-byte
registers of the STS series are little-endian. A servo ignores a packet whose checksum is wrong,
so a corrupted request shows up as a missing answer: every read here has a deadline, and a servo that
does not answer fails with :class:`FeetechTimeoutError` naming it, never a hang. A sync read is asked
again on such a transport error (timeout, checksum, short answer) up to ``SYNC_READ_ATTEMPTS`` times:
one garbled answer on a noisy bus must not end a control loop reading it many times a second. A
status error bit (overload, overheat, ...) is no transport error: the servo's data is good, and
:meth:`FeetechBus.sync_read_status` returns it beside the bits set.

A :class:`FeetechBus` may be shared by threads (a control loop and a safety monitor): each request
and its answers are one transaction under the bus's lock, so two requests never interleave on the
half-duplex wire.

Instructions used: ``PING``, ``READ``, ``WRITE`` (answered by the addressed servo), ``SYNC_WRITE``
(one packet to the broadcast id writes the same registers of many servos; not answered) and
``SYNC_READ`` (one packet, then each listed servo answers in turn).
"""

from __future__ import annotations

import fcntl
import logging
import os
import select
import termios
import threading
import time
import tty
from collections.abc import Mapping, Sequence

from infinirl.realworld.driver import RobotError

__all__ = [
    "BROADCAST_ID",
    "HEADER",
    "Instruction",
    "Register",
    "STS3215_MODEL_NUMBER",
    "FeetechBus",
    "FeetechChecksumError",
    "FeetechError",
    "FeetechStatusError",
    "FeetechTimeoutError",
    "FeetechTransportError",
    "PortBusyError",
    "SYNC_READ_ATTEMPTS",
    "SerialPort",
    "checksum",
    "decode_sign_magnitude",
    "encode_packet",
    "encode_sign_magnitude",
    "read_packet",
    "status_bits",
    "u16",
]

logger = logging.getLogger(__name__)

BROADCAST_ID = 0xFE
HEADER = b"\xff\xff"
STS3215_MODEL_NUMBER = 777
TICKS_PER_TURN = 4096
SYNC_READ_ATTEMPTS = 3


class Instruction:
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83


class Register:
    """STS3215 control table: ``(address, size in bytes)``."""

    MODEL_NUMBER = (3, 2)
    ID = (5, 1)
    MIN_POSITION_LIMIT = (9, 2)
    MAX_POSITION_LIMIT = (11, 2)
    TORQUE_ENABLE = (40, 1)
    ACCELERATION = (41, 1)
    GOAL_POSITION = (42, 2)
    GOAL_SPEED = (46, 2)
    PRESENT_POSITION = (56, 2)
    PRESENT_SPEED = (58, 2)
    MOVING = (66, 1)


_STATUS_BITS = {0: "input voltage", 1: "angle sensor", 2: "overheat", 3: "overcurrent", 5: "overload"}


class FeetechError(RobotError):
    """The servo bus failed a transaction."""


class FeetechTransportError(FeetechError):
    """The bytes of an answer did not arrive intact (a transient fault worth asking again)."""


class PortBusyError(FeetechError):
    """Another process (or another bus in this one) holds the serial port."""


class FeetechTimeoutError(FeetechTransportError):
    """A servo did not answer within the deadline (wrong id, no power, unplugged, or it dropped a
    corrupted request)."""


class FeetechChecksumError(FeetechTransportError):
    """A reply arrived with a wrong checksum (noise on the bus, wrong baud rate)."""


class FeetechStatusError(FeetechError):
    """A servo answered with error bits set."""


def checksum(body: bytes) -> int:
    """The checksum of a packet's ``id length instruction/error params`` bytes."""
    return ~sum(body) & 0xFF


def encode_packet(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A request packet, header and checksum included."""
    if not 0 <= servo_id <= BROADCAST_ID:
        raise ValueError(f"servo id must be 0..{BROADCAST_ID}, got {servo_id}")
    body = bytes([servo_id, len(params) + 2, instruction]) + bytes(params)
    return HEADER + body + bytes([checksum(body)])


def u16(value: int) -> bytes:
    """A 2-byte register value, little-endian (STS series)."""
    if not 0 <= value <= 0xFFFF:
        raise ValueError(f"a 2-byte register takes 0..65535, got {value}")
    return bytes([value & 0xFF, value >> 8])


def decode_sign_magnitude(raw: bytes, sign_bit: int = 15) -> int:
    """A little-endian register whose bit ``sign_bit`` is the sign (STS speeds, and present
    positions, which read below 0 when a joint is pushed past the encoder's zero)."""
    value = int.from_bytes(raw, "little")
    magnitude = value & ((1 << sign_bit) - 1)
    return -magnitude if value >> sign_bit & 1 else magnitude


def encode_sign_magnitude(value: int, size: int = 2, sign_bit: int = 15) -> bytes:
    """The inverse of :func:`decode_sign_magnitude`."""
    magnitude = abs(int(value))
    if magnitude >> sign_bit:
        raise ValueError(f"{value} does not fit a sign-magnitude register with the sign at bit {sign_bit}")
    return (magnitude | (1 << sign_bit if value < 0 else 0)).to_bytes(size, "little")


def status_bits(error: int) -> tuple[str, ...]:
    """The names of the error bits set in a status packet's error byte."""
    return tuple(name for bit, name in _STATUS_BITS.items() if error >> bit & 1) or ((f"{error:#04x}",) if error
                                                                                       else ())


class SerialPort:
    """A raw tty (8N1, no flow control, no echo, no line processing) with deadline-bounded reads.

    The port is held exclusively (``flock``, as pyserial's ``exclusive=True``): a second process
    writing to the same bus would interleave its packets with ours and both would read each other's
    answers. A port already held fails at once with :class:`PortBusyError`."""

    def __init__(self, path: str, baudrate: int) -> None:
        speed = getattr(termios, f"B{baudrate}", None)
        if speed is None:
            raise ValueError(f"baud rate {baudrate} is not one this system's termios supports")
        self.path = path
        try:
            self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as error:
            raise FeetechError(f"cannot open servo bus port {path}: {error.strerror}; check the path and "
                               "that this user may open it (group dialout)") from error
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            os.close(self._fd)
            raise PortBusyError(f"servo bus port {path} is in use by another program (or another run of this "
                                "one); close it first") from error
        try:
            tty.setraw(self._fd)
            attributes = termios.tcgetattr(self._fd)
            attributes[4] = attributes[5] = speed  # input and output speed
            attributes[2] &= ~termios.CRTSCTS
            attributes[2] |= termios.CLOCAL | termios.CREAD
            termios.tcsetattr(self._fd, termios.TCSANOW, attributes)
        except (OSError, termios.error) as error:
            os.close(self._fd)
            raise FeetechError(f"{path} is not a serial port this system can configure: {error}") from error

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            _, writable, _ = select.select([], [self._fd], [], 1.0)
            if not writable:
                raise FeetechTimeoutError(f"{self.path} does not accept data (1 s); is the adapter still plugged in?")
            view = view[os.write(self._fd, view):]

    def read(self, size: int, deadline: float) -> bytes:
        """Up to ``size`` bytes, fewer only if ``deadline`` (``time.monotonic()``) passes first."""
        data = bytearray()
        while len(data) < size:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            readable, _, _ = select.select([self._fd], [], [], remaining)
            if readable:
                chunk = os.read(self._fd, size - len(data))
                if not chunk:
                    raise FeetechError(f"{self.path} was closed by the other end")
                data += chunk
        return bytes(data)

    def discard_input(self) -> None:
        """Drop bytes left over from an earlier, failed transaction."""
        termios.tcflush(self._fd, termios.TCIFLUSH)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def read_packet(port: SerialPort, deadline: float, what: str) -> tuple[int, int, bytes]:
    """One status packet -> ``(id, error byte, params)``; bytes before a header are skipped (line
    noise). ``what`` names the awaited answer in the errors."""
    window = b""
    while window != HEADER:
        byte = port.read(1, deadline)
        if not byte:
            raise FeetechTimeoutError(f"no answer from {what} on {port.path}; check the id, power and wiring")
        window = (window + byte)[-2:]
    head = port.read(2, deadline)
    if len(head) < 2 or head[1] < 2:
        raise FeetechTimeoutError(f"incomplete answer from {what} on {port.path}")
    servo_id, length = head
    rest = port.read(length, deadline)
    if len(rest) < length:
        raise FeetechTimeoutError(f"incomplete answer from {what} on {port.path} ({len(rest)} of {length} bytes)")
    body = bytes(head) + rest[:-1]
    if checksum(body) != rest[-1]:
        raise FeetechChecksumError(f"answer from {what} on {port.path} has checksum {rest[-1]:#04x}, expected "
                                   f"{checksum(body):#04x} (noise on the bus or a wrong baud rate)")
    return servo_id, rest[0], rest[1:-1]


class FeetechBus:
    """Transactions on one servo bus. ``timeout_s`` bounds the wait for each answer."""

    def __init__(self, port: str, *, baudrate: int = 1_000_000, timeout_s: float = 0.1) -> None:
        self.timeout_s = float(timeout_s)
        self._port = SerialPort(port, baudrate)
        self._lock = threading.RLock()  # one request and its answers at a time (see the module docstring)

    @property
    def path(self) -> str:
        return self._port.path

    def close(self) -> None:
        with self._lock:
            self._port.close()

    def ping(self, servo_id: int) -> None:
        """Returns if servo ``servo_id`` answers; :class:`FeetechTimeoutError` otherwise."""
        self._transact(servo_id, Instruction.PING, b"")

    def read(self, servo_id: int, register: tuple[int, int]) -> bytes:
        address, size = register
        return self._transact(servo_id, Instruction.READ, bytes([address, size]), expect=size)

    def write(self, servo_id: int, register: tuple[int, int], data: bytes) -> None:
        """Write and wait for the servo's acknowledgement."""
        address, size = _check_size(register, data)
        self._transact(servo_id, Instruction.WRITE, bytes([address]) + data)

    def sync_write(self, register: tuple[int, int], values: Mapping[int, bytes]) -> None:
        """Write the same register of several servos in one unanswered packet (returns at once)."""
        address, size = register
        params = bytearray([address, size])
        for servo_id, data in values.items():
            _check_size(register, data)
            params += bytes([servo_id]) + data
        with self._lock:
            self._port.write(encode_packet(BROADCAST_ID, Instruction.SYNC_WRITE, bytes(params)))

    def sync_read(self, register: tuple[int, int], servo_ids: Sequence[int]) -> dict[int, bytes]:
        """One register of several servos: one request, one answer per servo in the listed order.
        Status error bits are logged, not raised (:meth:`sync_read_status` returns them)."""
        values, errors = self.sync_read_status(register, servo_ids)
        for servo_id, bits in errors.items():
            logger.warning("servo %d on %s reports: %s", servo_id, self.path, ", ".join(bits))
        return values

    def sync_read_status(self, register: tuple[int, int], servo_ids: Sequence[int], *,
                         attempts: int = SYNC_READ_ATTEMPTS) -> tuple[dict[int, bytes], dict[int, tuple[str, ...]]]:
        """``(values, errors)``: each servo's register, and the status error bits of each servo that
        set some (its value is still good). A transport error is asked again, up to ``attempts``
        requests in all, then raised."""
        for attempt in range(1, attempts + 1):
            try:
                with self._lock:
                    return self._sync_read_once(register, servo_ids)
            except FeetechTransportError as error:
                if attempt == attempts:
                    raise
                logger.warning("sync read on %s failed (%s); asking again (%d/%d)", self.path, error, attempt + 1,
                               attempts)
        raise AssertionError("unreachable")

    def _sync_read_once(self, register: tuple[int, int],
                        servo_ids: Sequence[int]) -> tuple[dict[int, bytes], dict[int, tuple[str, ...]]]:
        address, size = register
        self._port.discard_input()
        self._port.write(encode_packet(BROADCAST_ID, Instruction.SYNC_READ, bytes([address, size, *servo_ids])))
        values: dict[int, bytes] = {}
        errors: dict[int, tuple[str, ...]] = {}
        waiting = list(servo_ids)
        while waiting:  # a servo that does not answer is skipped by the next one's answer
            try:
                answered_id, error, params = self._status(time.monotonic() + self.timeout_s, f"servo {waiting[0]}",
                                                          size, raise_errors=False)
            except FeetechTimeoutError:
                break
            if answered_id not in waiting:
                raise FeetechError(f"servo {answered_id} on {self.path} answered a sync read of {list(servo_ids)}")
            values[answered_id] = params
            if error:
                errors[answered_id] = status_bits(error)
            waiting = waiting[waiting.index(answered_id) + 1:]
        missing = [servo_id for servo_id in servo_ids if servo_id not in values]
        if missing:
            raise FeetechTimeoutError(f"no answer from servos {missing} on {self.path} to a sync read; check their "
                                      "ids, power and wiring")
        return values, errors

    def _transact(self, servo_id: int, instruction: int, params: bytes, expect: int = 0) -> bytes:
        with self._lock:
            self._port.discard_input()
            self._port.write(encode_packet(servo_id, instruction, params))
            return self._answer(servo_id, time.monotonic() + self.timeout_s, expect)

    def _answer(self, servo_id: int, deadline: float, expect: int) -> bytes:
        answered_id, _, params = self._status(deadline, f"servo {servo_id}", expect)
        if answered_id != servo_id:
            raise FeetechError(f"expected an answer from servo {servo_id} on {self.path}, got one from {answered_id}")
        return params

    def _status(self, deadline: float, what: str, expect: int, *,
                raise_errors: bool = True) -> tuple[int, int, bytes]:
        answered_id, error, params = read_packet(self._port, deadline, what)
        if error and raise_errors:
            raise FeetechStatusError(f"servo {answered_id} on {self.path} reports: {', '.join(status_bits(error))}")
        if len(params) != expect:
            raise FeetechTransportError(f"servo {answered_id} on {self.path} answered {len(params)} bytes, expected "
                                        f"{expect}")
        return answered_id, error, params


def _check_size(register: tuple[int, int], data: bytes) -> tuple[int, int]:
    if len(data) != register[1]:
        raise ValueError(f"register at address {register[0]} takes {register[1]} bytes, got {len(data)}")
    return register
