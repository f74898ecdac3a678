"""The SO-101 arm (SO-ARM100/101, LeRobot): what its simulated and its real driver share.

Five arm joints and a gripper, each driven by a Feetech STS3215 servo (ids 1-6). Both drivers take
the same commands (``joint_position`` mode: five joint angles in radians, then the gripper, 0 closed
to 1 open), so a policy trained on the simulated arm drives the real one unchanged.
"""

from __future__ import annotations

import numpy as np

from infinirl.realworld.driver import CameraSpec, RobotSpec

__all__ = [
    "SO101_JOINT_HIGH",
    "SO101_JOINT_LOW",
    "SO101_JOINT_NAMES",
    "SO101_MAX_JOINT_VELOCITY",
    "SO101_WORKSPACE_HIGH",
    "SO101_WORKSPACE_LOW",
    "so101_spec",
]

SO101_JOINT_NAMES = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
# The joint ranges of the arm's published MJCF model (radians), which calibration reproduces on a real arm.
SO101_JOINT_LOW = np.array([-1.91986, -1.74533, -1.69, -1.65806, -2.74385])
SO101_JOINT_HIGH = np.array([1.91986, 1.74533, 1.69, 1.65806, 2.84121])
# Well under the STS3215's no-load speed (about 0.22 s per 60 degrees at 7.4 V), as loaded joints are slower.
SO101_MAX_JOINT_VELOCITY = np.full(5, 3.0)
# Reachable box in front of the base (metres, base frame), as the LeRobot MuJoCo model bounds its IK targets.
SO101_WORKSPACE_LOW = np.array([0.1, -0.3, 0.0])
SO101_WORKSPACE_HIGH = np.array([0.5, 0.3, 0.4])


def so101_spec(*, kind: str, control_hz: float, joint_low: np.ndarray = SO101_JOINT_LOW,
               joint_high: np.ndarray = SO101_JOINT_HIGH, cameras: tuple[CameraSpec, ...] = ()) -> RobotSpec:
    """The spec of an SO-101 arm in ``joint_position`` mode with a gripper."""
    return RobotSpec(
        kind=kind,
        dof=len(SO101_JOINT_NAMES),
        control_hz=control_hz,
        control_mode="joint_position",
        action_low=np.append(joint_low, 0.0),
        action_high=np.append(joint_high, 1.0),
        joint_low=joint_low,
        joint_high=joint_high,
        max_joint_velocity=SO101_MAX_JOINT_VELOCITY,
        workspace_low=SO101_WORKSPACE_LOW,
        workspace_high=SO101_WORKSPACE_HIGH,
        max_ee_speed=0.5,
        cameras=cameras,
        has_gripper=True,
        joint_names=SO101_JOINT_NAMES,
    )
