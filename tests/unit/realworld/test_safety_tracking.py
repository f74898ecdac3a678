"""A target may not run away from where the robot really is: the safety filter bounds how far a
command leads the measured pose (``max_lead_s``), beside the per-period step from the last target.
The pure filter, then the real SO-101 driver on the emulated bus with a blocked joint and a slow one."""

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from infinirl.realworld.driver import make_robot
from infinirl.realworld.feetech import Register
from infinirl.realworld.feetech_emulator import FeetechBusEmulator
from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
from infinirl.realworld.safety import SafeRobot, SafetyConfig, SafetyFilter, UnknownPoseError
from infinirl.realworld.so101 import so101_spec
from tests.unit.realworld.fake_robot import RecordingRobot, two_joint_spec

NO_DEADLINES = SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None)
TICKS_PER_RADIAN = 4096 / (2 * np.pi)


def wait_until(predicate, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()


def test_a_target_leads_the_measured_pose_by_at_most_the_lead_window():
    spec = so101_spec(kind="test_so101", control_hz=20.0)
    safety = SafetyFilter(spec, SafetyConfig(velocity_scale=0.5, max_lead_s=0.1))
    lead, step = 3.0 * 0.1, 0.5 * 3.0 / 20.0  # top speed 3 rad/s
    measured = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.6])
    # joint 0: the last target already a full window ahead (a blocked joint): it may not step further;
    # joint 1: far ahead (the arm was pushed back by hand): the target comes back to the window's edge;
    # joint 2: within the window, a normal step; the gripper: closed on an object held open, untouched.
    reference = np.array([lead, 1.0, 0.1, 0.0, 0.0, 0.0])
    command = np.array([lead + 1.0, 1.5, 1.0, 0.0, 0.0, 0.0])
    safe, records = safety(command, reference, measured)
    np.testing.assert_allclose(safe, [lead, lead, 0.1 + step, 0.0, 0.0, 0.0])
    assert sorted((r.kind, r.index) for r in records) == [("tracking", 0), ("tracking", 1), ("velocity", 0),
                                                          ("velocity", 1), ("velocity", 2)]
    # without a measured pose, or with the bound off, only the step from the last target applies
    np.testing.assert_allclose(safety(command, reference)[0][:2], [lead + step, 1.0 + step])
    off = SafetyFilter(spec, SafetyConfig(velocity_scale=0.5, max_lead_s=None))
    np.testing.assert_allclose(off(command, reference, measured)[0][:2], [lead + step, 1.0 + step])
    with pytest.raises(UnknownPoseError, match="measured pose is not finite at entries \\[3\\]"):
        safety(command, reference, np.array([0.0, 0.0, 0.0, np.nan, 0.0, np.nan]))
    with pytest.raises(ValueError, match="max_lead_s must be positive"):
        SafetyConfig(max_lead_s=0.0)


FINITE = st.floats(min_value=-3.0, max_value=3.0, allow_subnormal=False)


@settings(max_examples=300, deadline=None)
@given(reference=st.lists(FINITE, min_size=3, max_size=3), measured=st.lists(FINITE, min_size=3, max_size=3),
       command=st.lists(FINITE, min_size=3, max_size=3))
def test_from_a_measured_pose_within_the_limits_the_command_stays_in_its_window(reference, measured, command):
    spec = two_joint_spec(control_hz=20.0)  # joints in [-1, 1], 1 rad/s
    safety = SafetyFilter(spec, SafetyConfig(velocity_scale=0.5, max_lead_s=0.1))
    reference, measured, command = np.array(reference), np.array(measured), np.array(command)
    safe, _ = safety(command, reference, measured)
    lead, step = 0.1, 0.5 / 20.0
    inside = (measured[:2] >= -1) & (measured[:2] <= 1)
    assert np.all(np.abs(safe[:2] - measured[:2])[inside] <= lead * (1 + 1e-9))
    # where the last target lies in the window (and the limits), the step bound holds as well
    tracking = inside & (np.abs(reference[:2] - measured[:2]) <= lead) & (np.abs(reference[:2]) <= 1)
    assert np.all(np.abs(safe[:2] - reference[:2])[tracking] <= step * (1 + 1e-9))


def test_each_command_is_bounded_by_a_pose_observed_after_the_one_before():
    driver = RecordingRobot(spec=two_joint_spec(control_hz=20.0), joint_positions=(0.0, 0.0))
    robot = SafeRobot(driver, SafetyConfig(velocity_scale=1.0, max_lead_s=0.1, command_deadline_s=None,
                                           heartbeat_deadline_s=None))
    robot.connect()
    for _ in range(10):  # the robot does not move: the target stops a window ahead of it
        robot.act(np.array([1.0, 0.0, 1.0]))
    assert driver.commands[-1][0] == pytest.approx(0.1)
    # pushed past its target by hand: the next command reads where it is now, and the target comes
    # into the window around it (the arm is not pulled back the whole way)
    driver.joint_positions = np.array([0.5, 0.0])
    robot.act(np.array([1.0, 0.0, 1.0]))
    assert driver.commands[-1][0] == pytest.approx(0.5 - 0.1)
    driver.joint_positions = np.array([0.45, 0.0])
    robot.observe()  # an observation the caller made is used, not read again
    driver.joint_positions = np.array([-1.0, 0.0])
    robot.act(np.array([1.0, 0.0, 1.0]))
    assert driver.commands[-1][0] == pytest.approx(0.45)


@pytest.fixture
def emulator():
    # a calibrated gripper: the reset to the home pose (open) is short
    with FeetechBusEmulator(limits={6: (1900, 3300)}) as bus_emulator:
        yield bus_emulator


def so101_env(emulator, control_hz=50.0):
    robot = SafeRobot(make_robot("so101_feetech", port=emulator.path, control_hz=control_hz, reset_speed=4000),
                      NO_DEADLINES)
    robot.connect()
    return robot, RobotEnv(robot, RobotEnvSpec(observations=("proprio",), rewards={}, max_episode_steps=1000))


def test_a_blocked_joint_does_not_collect_a_target_it_jumps_to_when_it_clears(emulator):
    robot, env = so101_env(emulator)
    try:
        env.reset()
        emulator.block(2)  # shoulder_lift held where it is (a table, a hand)
        blocked_at = emulator.position(2)
        lead_ticks = 3.0 * robot.config.max_lead_s * TICKS_PER_RADIAN
        action = np.array([0.5, 1.0, 0.0, 0.0, 0.0, 1.0])  # delta mode: joint 0 at half speed, joint 1 full
        for _ in range(60):  # at 50 Hz, 60 full steps would be 1.8 rad of target
            env.step(action)
        assert emulator.position(2) == blocked_at
        goal = emulator.register(2, Register.GOAL_POSITION)
        assert 0 < goal - blocked_at <= lead_ticks + 1  # a window ahead, not the 1.8 rad the steps add up to
        assert robot.clip_counts["tracking"] > 0
        # the free joint kept following: the window does not hold back a joint that tracks its target
        assert emulator.register(1, Register.GOAL_POSITION) - 2048 > 0.5 * 1.5 * 60 / 50 * TICKS_PER_RADIAN * 0.99
        emulator.unblock(2)
        assert wait_until(lambda: emulator.position(2) == goal)  # the joint moves on: by the window, no more
        assert emulator.position(2) - blocked_at <= lead_ticks + 1
    finally:
        robot.close()


def test_a_slow_joint_still_reaches_its_target(emulator):
    robot, env = so101_env(emulator)
    try:
        env.reset()
        emulator.set_max_speed(3, 300.0)  # a loaded elbow: a fifth of the commanded speed (0.46 rad/s)
        target = 0.8
        command = env.last_observation.current_target(robot.spec)
        command[2] = target
        for _ in range(400):  # up to 8 s; the elbow needs under 2
            robot.act(command)
            time.sleep(robot.spec.control_period_s)
            if abs(robot.observe().joint_positions[2] - target) < 0.005:
                break
        assert robot.observe().joint_positions[2] == pytest.approx(target, abs=0.005)
        assert robot.clip_counts["tracking"] > 0  # it lagged beyond the window on the way, and got there
    finally:
        robot.close()


def test_the_run_config_sets_the_lead_window():
    from infinirl.config import ConfigError, to_dataclass
    from infinirl.runners.realworld_sac import robot_setup_of
    from infinirl.runners.realworld_sac_config import RealWorldSACConfig

    def setup(value):
        return robot_setup_of(to_dataclass(RealWorldSACConfig, {"robot": {"max_lead_s": value}}))

    assert setup(0.25).safety.max_lead_s == 0.25 and setup(None).safety.max_lead_s is None
    with pytest.raises(ConfigError, match="robot.max_lead_s"):
        setup(0.0)
