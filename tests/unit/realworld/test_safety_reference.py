"""The safety filter does not trust the pose it limits motion from: a reference that is not finite is
refused (the robot holds, nothing is sent), and one outside the limits still yields a command within
them. Property-tested over arbitrary references and commands, NaN and infinities included."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from infinirl.realworld.safety import SafeRobot, SafetyConfig, SafetyFilter, UnknownPoseError
from tests.unit.realworld.fake_robot import RecordingRobot, two_joint_spec

NO_DEADLINES = SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None)
# No subnormals: a library loaded by other tests may set flush-to-zero, which hypothesis refuses to draw under.
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=False, width=64)


def vectors(size):
    return st.lists(ANY_FLOAT, min_size=size, max_size=size).map(np.array)


@pytest.mark.parametrize("mode", ["joint_position", "ee_position"])
@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_the_filter_sends_finite_commands_within_the_limits_or_refuses(mode, data):
    spec = two_joint_spec(control_mode=mode, control_hz=20.0)
    safety = SafetyFilter(spec, SafetyConfig(velocity_scale=0.5))
    size = spec.target_size
    low, high = (spec.joint_low, spec.joint_high) if mode == "joint_position" else (spec.workspace_low,
                                                                                    spec.workspace_high)
    reference = data.draw(vectors(spec.command_size), label="reference")
    command = data.draw(vectors(spec.command_size), label="command")
    if not np.all(np.isfinite(reference)):
        with pytest.raises(UnknownPoseError, match="not finite"):
            safety(command, reference)
        return
    safe, _ = safety(command, reference)
    assert np.all(np.isfinite(safe))
    assert np.all(safe[:size] >= low) and np.all(safe[:size] <= high)
    assert 0.0 <= safe[size] <= 1.0
    top_speed = spec.max_joint_velocity if mode == "joint_position" else np.full(size, spec.max_ee_speed)
    step = 0.5 * top_speed / 20.0
    inside = (reference[:size] >= low) & (reference[:size] <= high)
    # from a pose within the limits the velocity bound holds as well (from one outside, the limit wins)
    moved = np.abs(safe[:size] - reference[:size])
    assert np.all(moved[inside] <= step[inside] * (1 + 1e-9))


def test_a_pose_that_is_not_finite_holds_the_robot_and_sends_nothing():
    driver = RecordingRobot(joint_positions=(np.inf, 0.0))
    robot = SafeRobot(driver, NO_DEADLINES)
    robot.connect()
    robot.hold()
    with pytest.raises(UnknownPoseError, match="inf"):
        robot.act(np.array([0.0, 0.0, 0.5]))
    assert driver.commands == [] and driver.calls[-1] == "hold"
    assert robot.event_counts["unknown_pose"] == 1
    driver.joint_positions = np.array([0.1, 0.0])  # the reading recovers: the next command re-reads the pose
    robot.act(np.array([0.0, 0.0, 0.5]))
    np.testing.assert_allclose(driver.commands[-1], [0.1 - 0.5 / 1000.0, 0.0, 0.5])


def test_a_stored_reference_that_is_not_finite_is_refused_too():
    driver = RecordingRobot(joint_positions=(0.0, np.nan))
    robot = SafeRobot(driver, NO_DEADLINES)
    robot.connect()  # the reference comes from the pose observed when connecting
    with pytest.raises(UnknownPoseError):
        robot.act(np.array([0.0, 0.0, 0.5]))
    assert driver.commands == [] and "hold" in driver.calls


def test_a_pose_beyond_the_limits_yields_a_command_within_them():
    driver = RecordingRobot(spec=two_joint_spec(control_hz=20.0), joint_positions=(1.5, 0.0))
    robot = SafeRobot(driver, NO_DEADLINES)
    robot.connect()
    robot.hold()
    robot.act(np.array([0.0, 0.0, 0.5]))
    sent = driver.commands[-1]
    assert np.all(np.isfinite(sent)) and -1.0 <= sent[0] <= 1.0
    assert robot.clip_counts["joint_limit"] >= 1
