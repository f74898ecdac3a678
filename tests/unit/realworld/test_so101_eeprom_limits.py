"""The SO-101 driver takes each servo's range from the servo: connect reads the EEPROM position
limits (Min_Position_Limit at 9, Max_Position_Limit at 11) off the wire, bounds every command with
them and maps the gripper's 0 .. 1 onto them; limits it cannot use refuse the connection."""

import logging
import math
import time

import numpy as np
import pytest

from infinirl.realworld.driver import RobotError, make_robot
from infinirl.realworld.feetech import BROADCAST_ID, FeetechBus, Instruction, Register, encode_packet, u16
from infinirl.realworld.feetech_emulator import FeetechBusEmulator
from infinirl.realworld.safety import SafeRobot, SafetyConfig

RADIANS_PER_TICK = 2 * math.pi / 4096


def wait_until(predicate, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()
GRIPPER_LIMITS = (1900, 3300)
SHOULDER_LIFT_LIMITS = (1500, 2600)  # narrower than the model's +-1.745 rad (2048 -+ 1137)


def test_limits_are_read_off_the_wire_and_bound_commands_and_the_gripper():
    with FeetechBusEmulator(limits={2: SHOULDER_LIFT_LIMITS, 6: GRIPPER_LIMITS}) as emulator:
        arm = make_robot("so101_feetech", port=emulator.path)
        before = arm.spec.joint_high[1]
        arm.connect()
        try:
            # one sync read of both registers (address 9, 4 bytes) of the six servos
            assert encode_packet(BROADCAST_ID, Instruction.SYNC_READ, bytes([9, 4, 1, 2, 3, 4, 5, 6])) in \
                emulator.requests
            assert arm.position_limits[2] == SHOULDER_LIFT_LIMITS and arm.position_limits[6] == GRIPPER_LIMITS
            assert arm.position_limits[1] == (0, 4095)  # the factory's: the model's range stays the bound
            assert before > 1.7 and arm.spec.joint_high[1] == pytest.approx((2600 - 2048) * RADIANS_PER_TICK)
            assert arm.spec.joint_low[1] == pytest.approx((1500 - 2048) * RADIANS_PER_TICK)
            goals = arm.goal_ticks(np.array([0.0, 1.5, 0.0, 0.0, 0.0, 0.0]))
            assert goals[2] == u16(2600) and goals[6] == u16(GRIPPER_LIMITS[0])  # closed: the low limit
            assert arm.goal_ticks(np.array([0.0, -1.5, 0.0, 0.0, 0.0, 1.0]))[6] == u16(GRIPPER_LIMITS[1])
            arm.act(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.5]))
            # halfway between the limits (a sync write is unanswered: the emulator applies it on its own thread)
            assert wait_until(lambda: emulator.register(6, Register.GOAL_POSITION) == 2600)
            arm.stop()
            assert wait_until(lambda: emulator.register(6, Register.TORQUE_ENABLE) == 0)  # limp: it stays pushed
            emulator.push(6, 1900 + 350)
            assert arm.observe().gripper == pytest.approx(0.25)
        finally:
            arm.close()


def test_the_safety_layer_clips_to_the_limits_the_servo_reported():
    with FeetechBusEmulator(limits={2: SHOULDER_LIFT_LIMITS}) as emulator:
        robot = SafeRobot(make_robot("so101_feetech", port=emulator.path),
                          SafetyConfig(velocity_scale=1.0, max_lead_s=None, command_deadline_s=None,
                                       heartbeat_deadline_s=None))
        robot.connect()
        try:
            high = (2600 - 2048) * RADIANS_PER_TICK
            sent = robot.observe().current_target(robot.spec)
            for _ in range(40):  # walk up to the servo's limit, then ask past it
                sent = robot.act(np.where(np.arange(6) == 1, 1.5, sent))
            assert sent[1] == pytest.approx(high) and robot.clip_counts["joint_limit"] > 0
        finally:
            robot.close()


@pytest.mark.parametrize(("limits", "message"), [
    ({4: (3000, 1000)}, "servo 4 has Min_Position_Limit 3000 >= Max_Position_Limit 1000 (inverted"),
    ({6: (0, 0)}, "servo 6 has Min_Position_Limit 0 >= Max_Position_Limit 0"),
    ({3: (100, 5000)}, "servo 3 has Max_Position_Limit 5000, beyond one turn"),
    ({1: (100, 200)}, "servo 1's limits 100..200 leave nothing of its calibrated range 797..3299"),
])
def test_limits_it_cannot_use_refuse_the_connection_naming_the_servo(limits, message):
    with FeetechBusEmulator(limits=limits) as emulator:
        arm = make_robot("so101_feetech", port=emulator.path)
        with pytest.raises(RobotError, match=message.replace("(", r"\(")) as error:
            arm.connect()
        assert "\n" not in str(error.value) and "recalibrate" in str(error.value)
        assert [emulator.register(i, Register.TORQUE_ENABLE) for i in range(1, 7)] == [0] * 6  # never armed
        FeetechBus(emulator.path).close()  # the port was let go


def test_a_gripper_with_the_factory_limits_is_reported(caplog):
    with FeetechBusEmulator() as emulator:
        arm = make_robot("so101_feetech", port=emulator.path)
        with caplog.at_level(logging.WARNING, logger="infinirl.realworld.so101_feetech"):
            arm.connect()
        arm.close()
    assert "gripper servo 6 has the factory position limits 0..4095" in caplog.text
