"""The driver interface: spec checks, command layout, the registry and discovery."""

import numpy as np
import pytest

from infinirl.realworld.driver import ROBOT_DRIVERS, RobotObservation, RobotSpec, discover
from infinirl.realworld.so101 import so101_spec


def test_spec_checks_its_arrays_and_modes():
    with pytest.raises(ValueError, match="joint_low must have 2 entries"):
        RobotSpec(kind="x", dof=2, control_hz=10, control_mode="joint_position", action_low=[0, 0],
                  action_high=[1, 1], joint_low=[0], joint_high=[1, 1], max_joint_velocity=[1, 1])
    with pytest.raises(ValueError, match="control_mode must be one of"):
        RobotSpec(kind="x", dof=1, control_hz=10, control_mode="torque", action_low=[0], action_high=[1],
                  joint_low=[0], joint_high=[1], max_joint_velocity=[1])
    with pytest.raises(ValueError, match="needs workspace_low/high"):
        RobotSpec(kind="x", dof=1, control_hz=10, control_mode="ee_position", action_low=[0] * 3,
                  action_high=[1] * 3, joint_low=[0], joint_high=[1], max_joint_velocity=[1])


def test_command_layout_and_present_target():
    spec = so101_spec(kind="so101", control_hz=20)
    assert spec.command_size == 6 and spec.action_high[-1] == 1.0
    with pytest.raises(ValueError, match=r"5 joint angles \+ gripper"):
        spec.check_command(np.zeros(5))
    observation = RobotObservation(joint_positions=np.arange(5.0), gripper=0.25)
    np.testing.assert_array_equal(observation.current_target(spec), [0, 1, 2, 3, 4, 0.25])


def test_registry_and_discovery():
    assert {"sim_so101", "sim_sawyer", "so101_feetech"} <= set(ROBOT_DRIVERS.names())
    found = discover({"sim_so101": {"instances": 2, "control_hz": 10}, "sim_sawyer": {"instances": 1}})
    assert [(robot.kind, robot.name) for robot in found] == [
        ("sim_sawyer", "sim_sawyer/0"), ("sim_so101", "sim_so101/0"), ("sim_so101", "sim_so101/1")]
    assert found[2].options == {"control_hz": 10, "seed": 1000}
    with pytest.raises(ValueError, match="unknown robot driver 'sim_so100'.*did you mean 'sim_so101'"):
        discover({"sim_so100": {}})
