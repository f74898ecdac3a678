"""A driver that moves nothing: it reports a pose the test sets and records every call, so what reached
the robot is asserted exactly (no simulator, no threads)."""

from __future__ import annotations

import numpy as np

from infinirl.realworld.driver import RobotDriver, RobotObservation, RobotSpec


def two_joint_spec(*, control_mode: str = "joint_position", control_hz: float = 1000.0) -> RobotSpec:
    """Two joints in [-1, 1] and a gripper; 1 rad/s and 1 m/s top speed."""
    if control_mode == "joint_position":
        low, high = [-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]
    else:
        low, high = [-0.5, -0.5, 0.0, 0.0], [0.5, 0.5, 0.5, 1.0]
    return RobotSpec(kind="fake_arm", dof=2, control_hz=control_hz, control_mode=control_mode, action_low=low,
                     action_high=high, joint_low=[-1.0, -1.0], joint_high=[1.0, 1.0], max_joint_velocity=[1.0, 1.0],
                     workspace_low=[-0.5, -0.5, 0.0], workspace_high=[0.5, 0.5, 0.5], max_ee_speed=1.0,
                     has_gripper=True)


class RecordingRobot(RobotDriver):
    """Observes ``joint_positions`` / ``ee_position`` / ``gripper`` (set them between calls); ``commands``
    holds every command ``act`` received, ``calls`` the name of every call."""

    def __init__(self, spec: RobotSpec | None = None, *, joint_positions=(0.2, -0.3), ee_position=(0.1, -0.2, 0.3),
                 gripper: float | None = 0.4) -> None:
        self._spec = spec or two_joint_spec()
        self.joint_positions = np.asarray(joint_positions, np.float64)
        self.ee_position = np.asarray(ee_position, np.float64)
        self.gripper = gripper
        self.commands: list[np.ndarray] = []
        self.calls: list[str] = []

    @property
    def spec(self) -> RobotSpec:
        return self._spec

    def connect(self) -> None:
        self.calls.append("connect")

    def observe(self) -> RobotObservation:
        return RobotObservation(joint_positions=self.joint_positions.copy(), ee_position=self.ee_position.copy(),
                                gripper=self.gripper)

    def act(self, command: np.ndarray) -> None:
        self.calls.append("act")
        self.commands.append(np.array(command, np.float64))

    def reset(self) -> RobotObservation:
        self.calls.append("reset")
        return self.observe()

    def hold(self) -> None:
        self.calls.append("hold")

    def stop(self) -> None:
        self.calls.append("stop")

    def close(self) -> None:
        self.calls.append("close")
