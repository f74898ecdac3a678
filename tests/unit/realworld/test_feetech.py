"""The Feetech STS3215 bus down to the wire, against the pty emulator of a six-servo bus."""

import time

import numpy as np
import pytest

from infinirl.realworld.driver import RobotError, RobotStoppedError, discover, make_robot
from infinirl.realworld.feetech import (
    FeetechBus,
    FeetechChecksumError,
    FeetechTimeoutError,
    Instruction,
    Register,
    SerialPort,
    decode_sign_magnitude,
    encode_packet,
    read_packet,
    u16,
)
from infinirl.realworld.feetech_emulator import FeetechBusEmulator
from infinirl.realworld.so101_feetech import CONNECT_PING_ATTEMPTS

# Packets worked out by hand from the protocol: checksum = ~(id + length + instruction + params) & 0xFF.
PING_1 = bytes.fromhex("ff ff 01 02 01 fb")  # ~(1 + 2 + 1) = ~0x04
READ_POSITION_1 = bytes.fromhex("ff ff 01 04 02 38 02 be")  # ~(1 + 4 + 2 + 0x38 + 2) = ~0x41
WRITE_GOAL_2048_1 = bytes.fromhex("ff ff 01 05 03 2a 00 08 c4")  # ~(1 + 5 + 3 + 0x2a + 0 + 8) = ~0x3b
# goal 2048 to servo 1, 1024 to servo 2: ~(0xfe + 0x0a + 0x83 + 0x2a + 2 + 1 + 0 + 8 + 2 + 0 + 4) = ~0xc6
SYNC_WRITE_GOALS = bytes.fromhex("ff ff fe 0a 83 2a 02 01 00 08 02 00 04 39")
SYNC_READ_POSITIONS = bytes.fromhex("ff ff fe 06 82 38 02 01 02 3c")  # ~(0xfe + 6 + 0x82 + 0x38 + 2 + 1 + 2)
# torque off on servos 1-6: ~(0xfe + 0x10 + 0x83 + 0x28 + 1 + (1 + 2 + 3 + 4 + 5 + 6)) = ~0xcf
TORQUE_OFF_ALL = bytes.fromhex("ff ff fe 10 83 28 01 01 00 02 00 03 00 04 00 05 00 06 00 30")


def wait_until(predicate, timeout_s=5.0):
    """True once ``predicate()`` is (the emulator applies unanswered packets on its own thread)."""
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()


def torque(emulator):
    return [emulator.register(i, Register.TORQUE_ENABLE) for i in range(1, 7)]


@pytest.fixture
def emulator():
    with FeetechBusEmulator() as bus_emulator:
        yield bus_emulator


@pytest.fixture
def bus(emulator):
    feetech_bus = FeetechBus(emulator.path, timeout_s=0.1)
    yield feetech_bus
    feetech_bus.close()


def test_packets_match_hand_computed_bytes():
    assert encode_packet(1, Instruction.PING) == PING_1
    assert encode_packet(1, Instruction.READ, bytes([0x38, 2])) == READ_POSITION_1
    assert encode_packet(1, Instruction.WRITE, bytes([0x2A]) + u16(2048)) == WRITE_GOAL_2048_1
    assert u16(2048) == b"\x00\x08"
    assert decode_sign_magnitude(bytes([0x10, 0x80])) == -16 and decode_sign_magnitude(bytes([0x10, 0x00])) == 16


def test_transactions_on_the_wire(emulator, bus):
    bus.ping(1)
    assert bus.read(1, Register.PRESENT_POSITION) == u16(2048)
    bus.write(1, Register.GOAL_POSITION, u16(2048))
    bus.sync_write(Register.GOAL_POSITION, {1: u16(2048), 2: u16(1024)})
    assert bus.sync_read(Register.PRESENT_POSITION, [1, 2]) == {1: u16(2048), 2: u16(2048)}  # torque off: no motion
    assert emulator.requests == [PING_1, READ_POSITION_1, WRITE_GOAL_2048_1, SYNC_WRITE_GOALS, SYNC_READ_POSITIONS]


def test_servo_moves_toward_goal_only_with_torque_on(emulator, bus):
    bus.write(3, Register.GOAL_POSITION, u16(2300))
    time.sleep(0.05)
    assert emulator.position(3) == 2048
    bus.write(3, Register.TORQUE_ENABLE, b"\x01")
    deadline = time.monotonic() + 5.0
    while emulator.position(3) != 2300 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert int.from_bytes(bus.read(3, Register.PRESENT_POSITION), "little") == 2300


def test_corrupted_answer_is_a_checksum_error(emulator, bus):
    emulator.corrupt_replies(1)
    with pytest.raises(FeetechChecksumError, match="servo 2"):
        bus.read(2, Register.PRESENT_POSITION)
    assert bus.read(2, Register.PRESENT_POSITION) == u16(2048)  # the bus recovers on the next transaction


def test_corrupted_request_is_ignored_and_times_out(emulator):
    port = SerialPort(emulator.path, 1_000_000)
    try:
        broken = bytearray(PING_1)
        broken[-1] ^= 0x01
        port.write(bytes(broken))
        with pytest.raises(FeetechTimeoutError, match="servo 1"):
            read_packet(port, time.monotonic() + 0.1, "servo 1")
    finally:
        port.close()
    assert emulator.ignored_requests == 1


def test_missing_servo_times_out_with_its_id(emulator, bus):
    with pytest.raises(FeetechTimeoutError, match="servo 9.*check the id"):
        bus.ping(9)
    emulator.unplug(4)
    with pytest.raises(FeetechTimeoutError, match=r"servos \[4\]"):
        bus.sync_read(Register.PRESENT_POSITION, [3, 4, 5])


def test_unopenable_port_is_a_clear_error(tmp_path):
    with pytest.raises(RobotError, match="cannot open servo bus port"):
        FeetechBus(str(tmp_path / "ttyACM9"))


def test_arm_follows_commands_and_stop_turns_torque_off(emulator):
    arm = make_robot("so101_feetech", port=emulator.path, reset_speed=4000)
    arm.connect()
    try:
        assert wait_until(lambda: torque(emulator) == [1] * 6)
        observation = arm.reset()
        np.testing.assert_allclose(observation.joint_positions, 0.0, atol=0.05)
        command = np.array([0.3, -0.2, 0.1, 0.0, 0.0, 0.5])
        assert arm.goal_ticks(command)[1] == u16(2048 + round(0.3 * 4096 / (2 * np.pi)))
        arm.act(command)
        arrived = np.append(command[:5], 0.5)
        wait_until(lambda: np.allclose(np.append(arm.observe().joint_positions, arm.observe().gripper), arrived,
                                       atol=0.01))
        observation = arm.observe()
        np.testing.assert_allclose(observation.joint_positions, command[:5], atol=0.01)
        assert observation.gripper == pytest.approx(0.5, abs=0.01)
        arm.stop()
        assert wait_until(lambda: torque(emulator) == [0] * 6)
        assert emulator.requests[-1] == TORQUE_OFF_ALL
        with pytest.raises(RobotStoppedError):
            arm.act(command)
        arm.reset()  # re-arms
        assert wait_until(lambda: torque(emulator) == [1] * 6)
    finally:
        arm.close()
    assert wait_until(lambda: torque(emulator) == [0] * 6)


def test_arm_with_a_missing_servo_refuses_to_connect(emulator):
    emulator.unplug(5)
    arm = make_robot("so101_feetech", port=emulator.path, timeout_s=0.05)
    with pytest.raises(RobotError, match=r"servos \[5\] do not answer"):
        arm.connect()


def test_an_answer_lost_at_connect_is_asked_again_not_taken_for_a_missing_servo(emulator):
    emulator.corrupt_replies(CONNECT_PING_ATTEMPTS - 1)  # servo 1's first answers are garbled on the line
    arm = make_robot("so101_feetech", port=emulator.path, timeout_s=0.05)
    arm.connect()
    arm.stop()


def test_discovery_finds_the_arm_on_a_configured_port(emulator, tmp_path):
    found = discover({"so101_feetech": {"ports": [emulator.path, str(tmp_path / "nothing*")]}})
    assert [(robot.kind, robot.name) for robot in found] == [("so101_feetech", emulator.path)]
    assert discover() == []  # no port is scanned unless configured
