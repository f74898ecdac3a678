"""The env's hold action and non-finite actions: a NaN entry of a policy's action holds that entry for
one step (reported, never kept as the target or as ``last_action``), and :meth:`RobotEnv.hold_action`
commands the present target in both action modes."""

import numpy as np
import pytest

from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
from infinirl.realworld.safety import SafeRobot, SafetyConfig
from tests.unit.realworld.fake_robot import RecordingRobot, two_joint_spec

NO_DEADLINES = SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None)


def an_env(mode="delta", control_mode="joint_position", **driver):
    driver = RecordingRobot(two_joint_spec(control_mode=control_mode), **driver)
    robot = SafeRobot(driver, NO_DEADLINES)
    robot.connect()
    return RobotEnv(robot, RobotEnvSpec(observations=("proprio", "last_action"), action_mode=mode,
                                        rewards={})), driver


@pytest.mark.parametrize("mode", ["delta", "absolute"])
def test_a_nan_action_holds_those_entries_and_poisons_nothing(mode):
    env, driver = an_env(mode)
    env.reset()
    step = env.step(np.array([np.nan, 0.5, np.inf]))
    assert step.non_finite and env.non_finite_actions == 1
    assert np.all(np.isfinite(step.obs["state"])) and np.all(np.isfinite(env.last_action))
    sent = driver.commands[-1]
    assert np.all(np.isfinite(sent))
    assert sent[0] == pytest.approx(0.2) and sent[2] == pytest.approx(0.4)  # held: the observed target
    step = env.step(np.array([1.0, 0.5, 1.0]))
    assert not step.non_finite and np.all(np.isfinite(step.obs["state"]))
    assert driver.commands[-1][0] > 0.2 + 1e-6  # joint 0 moves again


@pytest.mark.parametrize("control_mode", ["joint_position", "ee_position"])
@pytest.mark.parametrize("mode", ["delta", "absolute"])
def test_the_hold_action_commands_the_observed_target(mode, control_mode):
    env, driver = an_env(mode, control_mode)
    env.reset()
    observed = env.robot.observe().current_target(env.robot_spec)
    hold = env.hold_action()
    assert np.all(np.abs(hold) <= 1.0)
    if mode == "delta":
        assert np.all(hold[:env.robot_spec.target_size] == 0.0)
    for _ in range(2):
        env.step(env.hold_action())
        np.testing.assert_allclose(driver.commands[-1], observed, atol=1e-9)
    with pytest.raises(RuntimeError, match="reset"):
        RobotEnv(env.robot, env.spec).hold_action()


def test_the_target_is_the_command_the_safety_layer_sent():
    """A command the safety layer clips (here: too fast for one period) is not what the robot was
    told; the env's target, and so the next delta and the hold action, follow what was sent."""
    env, driver = an_env("absolute")
    env.reset()
    env.step(np.array([1.0, -1.0, 1.0]))
    sent = driver.commands[-1]
    assert env.robot.clip_counts["velocity"] > 0
    env.step(env.hold_action())
    np.testing.assert_allclose(driver.commands[-1], sent)  # held where it was sent, not pulled on
