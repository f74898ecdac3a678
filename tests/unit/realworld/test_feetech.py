"""The Feetech STS3215 bus down to the wire, against the pty emulator of a six-servo bus."""

import time

import numpy as np
import pytest

from infinirl.realworld.driver import RobotError, RobotStoppedError, discover, make_robot
from infinirl.realworld.feetech import (
    SYNC_READ_ATTEMPTS,
    FeetechBus,
    FeetechChecksumError,
    FeetechTimeoutError,
    Instruction,
    PortBusyError,
    Register,
    SerialPort,
    decode_sign_magnitude,
    encode_packet,
    read_packet,
    u16,
)
from infinirl.realworld.feetech_emulator import FeetechBusEmulator
from infinirl.realworld.safety import SafeRobot, SafetyConfig, ServoFaultError
from infinirl.realworld.so101_feetech import CONNECT_PING_ATTEMPTS, attached_so101_arms

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


def so101_loop(emulator, tmp_path, heartbeat_s):
    from infinirl.config import to_dataclass
    from infinirl.realworld.control_loop import RobotControlLoop
    from infinirl.runners.realworld_sac import env_spec_of, net_spec_of, robot_setup_of
    from infinirl.runners.realworld_sac_config import RealWorldSACConfig

    cfg = to_dataclass(RealWorldSACConfig, {
        "output_dir": str(tmp_path / "run"),
        "robot": {"kind": "so101_feetech", "options": {"port": emulator.path, "control_hz": 50.0, "reset_speed": 4000},
                  "heartbeat_deadline_s": heartbeat_s, "command_deadline_s": None},
        "task": {"max_episode_steps": 3, "observations": ["proprio"], "rewards": {}},
        "network": {"actor_hidden": [16], "critic_hidden": [16]}})
    return RobotControlLoop(robot_setup_of(cfg), env_spec_of(cfg), net_spec_of(cfg), seed=0)


def test_the_arm_stays_held_while_the_loop_idles_between_episodes(emulator, tmp_path):
    """Synchronous collection idles between episodes while the learner updates (and before the
    first); the idle is deliberate, so the heartbeat goes on and the arm keeps its torque."""
    loop = so101_loop(emulator, tmp_path, heartbeat_s=0.5)
    try:
        time.sleep(1.2)  # before the first episode
        assert loop.collect(1)
        time.sleep(1.2)  # the learner updating
        assert torque(emulator) == [1] * 6
        assert loop.robot.event_counts["heartbeat_stop"] == 0
        held = [emulator.position(i) for i in range(1, 7)]
        assert held == [emulator.register(i, Register.GOAL_POSITION) for i in range(1, 7)]  # holding in place
        assert loop.collect(1)
        assert loop.robot.event_counts["heartbeat_stop"] == 0
    finally:
        loop.close()


OVERLOAD = 1 << 5


def test_a_garbled_or_lost_sync_read_answer_is_asked_again(emulator, bus):
    ids = list(range(1, 7))
    emulator.corrupt_replies(1)  # one bad checksum
    assert sorted(bus.sync_read(Register.PRESENT_POSITION, ids)) == ids
    emulator.drop_replies(1)  # one answer lost: a timeout
    assert sorted(bus.sync_read(Register.PRESENT_POSITION, ids)) == ids
    requests = len(emulator.requests)
    emulator.corrupt_replies(6 * SYNC_READ_ATTEMPTS)  # a fault that persists is raised, after the attempts
    with pytest.raises(FeetechChecksumError):
        bus.sync_read(Register.PRESENT_POSITION, ids)
    assert len(emulator.requests) - requests == SYNC_READ_ATTEMPTS


def test_an_overload_bit_keeps_every_servos_data_and_names_the_servo(emulator, bus):
    emulator.set_status_error(3, OVERLOAD)
    values, errors = bus.sync_read_status(Register.PRESENT_POSITION, range(1, 7))
    assert sorted(values) == list(range(1, 7)) and values[3] == u16(2048)
    assert errors == {3: ("overload",)}


def test_an_overloaded_servo_holds_the_arm_and_ends_the_episode_not_the_loop(emulator, tmp_path):
    arm = SafeRobot(make_robot("so101_feetech", port=emulator.path, reset_speed=4000),
                    SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None))
    arm.connect()
    try:
        emulator.set_status_error(2, OVERLOAD)
        assert arm.driver.observe().info["servo_errors"] == {2: ("overload",)}
        with pytest.raises(ServoFaultError, match="servo 2: overload"):
            arm.observe()
        assert arm.event_counts["servo_error"] == 1 and torque(emulator) == [1] * 6  # held, not let go
    finally:
        arm.close()
    emulator.set_status_error(2, 0)
    loop = so101_loop(emulator, tmp_path, heartbeat_s=2.0)
    try:
        emulator.set_status_error(2, OVERLOAD)
        assert loop.collect(1) == []  # the first step's observation reports the overload
        assert loop.counts["safety_aborts"] == 1 and loop.robot.event_counts["servo_error"] == 1
        emulator.set_status_error(2, 0)
        assert loop.collect(1)
    finally:
        loop.close()


def test_two_threads_share_the_bus_without_mixing_answers(emulator, bus):
    import threading

    errors = []

    def read(register):
        try:
            for _ in range(50):
                assert len(bus.sync_read(register, range(1, 7))) == 6
                bus.ping(4)
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=read, args=(r,)) for r in (Register.PRESENT_POSITION, Register.MODEL_NUMBER)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []


def test_a_position_below_zero_is_read_as_sign_magnitude(emulator):
    arm = make_robot("so101_feetech", port=emulator.path)
    arm.connect()
    try:
        arm.stop()  # torque off: the joint stays where a hand puts it
        emulator.push(1, -5)
        assert emulator.register(1, Register.PRESENT_POSITION) == 0x8005  # on the wire: bit 15 is the sign
        observation = arm.observe()
        assert observation.joint_positions[0] == pytest.approx(arm.calibration[0].to_angle(-5))
        arm.hold()
        assert wait_until(lambda: emulator.register(1, Register.GOAL_POSITION) == 0)  # the nearest goal, not 32773
    finally:
        arm.close()


def test_a_port_is_opened_by_one_bus_only_and_discovery_says_it_is_in_use(emulator, bus, caplog):
    with pytest.raises(PortBusyError, match="in use"):
        FeetechBus(emulator.path)
    requests = len(emulator.requests)
    assert attached_so101_arms(ports=[emulator.path]) == []
    assert "in use" in caplog.text and len(emulator.requests) == requests  # not probed
    bus.close()
    assert [arm.name for arm in attached_so101_arms(ports=[emulator.path])] == [emulator.path]


def test_the_servos_speed_is_capped_at_the_specs_top_speed_outside_the_reset(emulator):
    arm = make_robot("so101_feetech", port=emulator.path, reset_speed=4000)
    top = round(float(arm.spec.max_joint_velocity.max()) * 4096 / (2 * np.pi))

    def speeds():
        return [emulator.register(i, Register.GOAL_SPEED) for i in range(1, 7)]

    arm.connect()
    try:
        assert wait_until(lambda: speeds() == [top] * 6)
        arm.reset()
        assert wait_until(lambda: speeds() == [top] * 6)  # not 0, the servo's unlimited speed
    finally:
        arm.close()
