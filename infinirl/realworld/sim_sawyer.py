"""The simulated Sawyer arm: a MetaWorld task (:class:`~infinirl.envs.metaworld_env.MetaWorldSubEnv`)
behind the driver interface, commanded in ``ee_position`` mode (hand xyz target, gripper 0 closed
to 1 open), paced in real time by :class:`SimulatedRobot`.

MetaWorld moves the hand's mocap body by at most ``METAWORLD_ACTION_SCALE`` metres per step of
``METAWORLD_STEP_S`` simulated seconds (SawyerXYZEnv's defaults: ``action_scale = 1/100``, five
frames of 2.5 ms). A control period runs as many MetaWorld steps as fit in it, each pushing the
hand toward the target as far as a step allows, so the simulated world advances one control period
per tick and the hand's top speed is that of MetaWorld's own actions. Joint angles are not exposed by
the MetaWorld adapter, so observations report ``joint_positions=None``.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import Any

import numpy as np

from infinirl.envs.gymnasium_env import use_headless_gl
from infinirl.realworld.driver import AttachedRobot, CameraSpec, RobotObservation, RobotSpec
from infinirl.realworld.sim_robot import SimulatedRobot, check_lockstep

__all__ = ["METAWORLD_ACTION_SCALE", "METAWORLD_STEP_S", "SAWYER_SPEC_LIMITS", "SawyerPlant", "SimSawyer",
           "attached_sim_sawyers", "camera_shape"]

METAWORLD_ACTION_SCALE = 0.01
METAWORLD_STEP_S = 0.0125
_NEVER_TRUNCATE = 10**12  # the robot runs until reset; episode lengths belong to the layer above


def camera_shape(image_size: int | Sequence[int]) -> tuple[int, int]:
    """``image_size`` as (height, width): an int is a square frame, a pair is (height, width), as a real
    camera streams (e.g. ``[480, 640]``) while training uses a smaller resize of it."""
    size = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
    if len(size) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size):
        raise ValueError(f"image_size must be a positive int or [height, width], got {image_size!r}")
    return size
# Sawyer's published joint limits (rad) and joint speed limits (rad/s), right_j0 .. right_j6.
SAWYER_SPEC_LIMITS = {
    "joint_low": np.array([-3.0503, -3.8095, -3.0426, -3.0439, -2.9761, -2.9761, -4.7124]),
    "joint_high": np.array([3.0503, 2.2736, 3.0426, 3.0439, 2.9761, 2.9761, 4.7124]),
    "max_joint_velocity": np.array([1.74, 1.328, 1.957, 1.957, 3.485, 3.485, 4.545]),
}
# MetaWorld's widest hand box (SawyerXYZEnv hand_low/hand_high of the v3 tasks), metres.
_WORKSPACE_LOW = np.array([-0.5, 0.40, 0.05])
_WORKSPACE_HIGH = np.array([0.5, 1.0, 0.5])


class SawyerPlant:
    """One MetaWorld task scene; driven by one thread."""

    def __init__(self, *, task: str, control_hz: float, image_size: int | Sequence[int] | None,
                 camera: str = "corner") -> None:
        height, width = camera_shape(image_size) if image_size else (64, 64)
        use_headless_gl()  # before MuJoCo is imported (see SO101Plant): frames are rendered from this env
        from infinirl.envs.metaworld_env import MetaWorldSubEnv

        self._env = MetaWorldSubEnv(task, obs_mode="state", camera=camera, image_size=(height, width),
                                    max_episode_steps=_NEVER_TRUNCATE)
        self._camera = camera
        self._steps_per_tick = max(1, round(1.0 / control_hz / METAWORLD_STEP_S))
        self._state: np.ndarray | None = None
        self._success = False
        cameras = (CameraSpec(name=camera, height=height, width=width),) if image_size else ()
        self.spec = RobotSpec(
            kind="sim_sawyer",
            dof=7,
            control_hz=control_hz,
            control_mode="ee_position",
            action_low=np.append(_WORKSPACE_LOW, 0.0),
            action_high=np.append(_WORKSPACE_HIGH, 1.0),
            workspace_low=_WORKSPACE_LOW,
            workspace_high=_WORKSPACE_HIGH,
            max_ee_speed=METAWORLD_ACTION_SCALE / METAWORLD_STEP_S,
            cameras=cameras,
            has_gripper=True,
            joint_names=tuple(f"right_j{index}" for index in range(7)),
            **SAWYER_SPEC_LIMITS,
        )

    def reset(self, seed: int) -> None:
        self._state = self._env.reset(seed=seed)["state"]
        self._success = False

    def apply(self, target: np.ndarray) -> None:
        grip = 1.0 - 2.0 * float(np.clip(target[-1], 0.0, 1.0))  # MetaWorld: +1 closes, -1 opens
        for _ in range(self._steps_per_tick):
            move = np.clip((target[:3] - self._state[:3]) / METAWORLD_ACTION_SCALE, -1.0, 1.0)
            step = self._env.step(np.append(move, grip).astype(np.float32))
            self._state = step.obs["state"]
            self._success = self._success or step.success

    def read(self) -> RobotObservation:
        state = self._state.astype(np.float64)
        return RobotObservation(joint_positions=None, ee_position=state[:3].copy(), gripper=float(state[3]),
                                info={"success": self._success, "state": state.copy()})

    def render(self) -> dict[str, np.ndarray]:
        return {self._camera: self._env.render()}

    def close(self) -> None:
        self._env.close()


class SimSawyer(SimulatedRobot):
    """MetaWorld's Sawyer on task ``task`` at ``control_hz`` in real time; ``image_size=None`` for no
    camera, ``[height, width]`` for a non-square one. ``info["success"]``: the task succeeded at some
    step since the last reset. ``lockstep``: one control period per command instead of per period of
    wall-clock time, for reproducible tests (:mod:`~infinirl.realworld.sim_robot`)."""

    def __init__(self, *, task: str = "reach-v3", control_hz: float = 20.0, image_size: int | Sequence[int] | None = 64,
                 camera: str = "corner", latency_s: float = 0.0, reset_s: float = 0.0, seed: int = 0,
                 lockstep: bool = False) -> None:
        super().__init__(partial(SawyerPlant, task=task, control_hz=control_hz, image_size=image_size, camera=camera),
                         latency_s=latency_s, reset_s=reset_s, seed=seed, lockstep=lockstep)

    @classmethod
    def check_options(cls, *, image_size: int | Sequence[int] | None = 64, lockstep: bool = False,
                      latency_s: float = 0.0, **_: Any) -> None:
        """The option values a config gives, checked before any worker builds the arm."""
        if image_size:
            camera_shape(image_size)
        check_lockstep(lockstep, latency_s)


def attached_sim_sawyers(*, instances: int = 0, seed: int = 0, **options: Any) -> list[AttachedRobot]:
    """The ``instances`` simulated Sawyers this node offers (arm ``i`` seeds from ``seed + 1000 * i``)."""
    return [
        AttachedRobot(kind="sim_sawyer", name=f"sim_sawyer/{index}", options={**options, "seed": seed + 1000 * index},
                      description="simulated Sawyer arm (MetaWorld, real-time)")
        for index in range(instances)
    ]
