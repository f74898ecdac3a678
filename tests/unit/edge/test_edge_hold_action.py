"""The edge's hold keeps the robot where it is from the first step of an episode: zero motion and the
gripper as observed in delta mode, the observed target in absolute mode (never the zero action, which
would move the gripper to half open or the arm to the middle of its range)."""

import numpy as np
import pytest

from infinirl.edge.edge_actor import hold_action
from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
from infinirl.realworld.safety import SafeRobot, SafetyConfig
from tests.unit.realworld.fake_robot import RecordingRobot, two_joint_spec


@pytest.mark.parametrize("mode", ["delta", "absolute"])
def test_holding_after_reset_commands_the_observed_target(mode):
    driver = RecordingRobot(two_joint_spec(), joint_positions=(0.6, -0.7), gripper=1.0)
    robot = SafeRobot(driver, SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None))
    robot.connect()
    env = RobotEnv(robot, RobotEnvSpec(observations=("proprio",), action_mode=mode, rewards={}))
    env.reset()
    observed = robot.observe().current_target(env.robot_spec)
    for _ in range(3):
        action = hold_action(env)
        assert action.dtype == np.float32 and action.shape == (env.action_dim,)
        env.step(action)
        np.testing.assert_allclose(driver.commands[-1], observed, atol=1e-6)
    if mode == "delta":
        assert np.all(hold_action(env)[:2] == 0.0)
