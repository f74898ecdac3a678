"""Simulated robots behave like real ones: wall-clock pacing that never speeds up, command
latency, resets that take time, camera frames; both embodiments behind one interface."""

import time

import numpy as np
import pytest

from infinirl.realworld.driver import RobotError, RobotStoppedError, make_robot
from infinirl.realworld.sim_sawyer import camera_shape


def wait_until(predicate, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()


def test_so101_follows_joint_targets_at_wall_clock_pace():
    robot = make_robot("sim_so101", control_hz=20.0, image_size=32)
    with robot:
        first = robot.observe()
        assert first.frames["front"].shape == (32, 32, 3) and first.frames["front"].dtype == np.uint8
        target = first.current_target(robot.spec)
        target[0] += 0.3
        started, start_tick = time.monotonic(), robot.observe().tick
        robot.act(target)
        assert wait_until(lambda: abs(robot.observe().joint_positions[0] - target[0]) < 0.05)
        time.sleep(0.2)
        ticks = robot.observe().tick - start_tick
        elapsed = time.monotonic() - started
        assert ticks <= elapsed * 20.0 + 2  # never faster than real time, however fast the simulator is
        assert robot.stats.commands_applied == 1 and robot.stats.frames >= 1
        assert robot.observe().info["success"] is False


def test_latency_delays_a_command_and_reset_takes_its_time():
    robot = make_robot("sim_so101", control_hz=50.0, image_size=None, latency_s=0.3, reset_s=0.2)
    started = time.monotonic()
    robot.connect()
    try:
        assert time.monotonic() - started >= 0.2  # the first episode's reset
        robot.act(robot.observe().current_target(robot.spec))
        assert robot.stats.commands_applied == 0  # not before its latency has passed
        assert wait_until(lambda: robot.stats.commands_applied == 1)
        started = time.monotonic()
        robot.reset()
        assert time.monotonic() - started >= 0.2 and robot.stats.resets == 2
    finally:
        robot.close()


def test_stop_refuses_commands_until_reset_and_close_is_final():
    robot = make_robot("sim_so101", control_hz=50.0, image_size=None)
    with pytest.raises(RobotError, match="not connected"):
        robot.observe()
    robot.connect()
    robot.stop()
    with pytest.raises(RobotStoppedError):
        robot.act(robot.observe().current_target(robot.spec))
    robot.reset()
    robot.act(robot.observe().current_target(robot.spec))
    with pytest.raises(ValueError, match=r"expects a command of shape \(6,\)"):
        robot.act(np.zeros(4))
    robot.close()
    with pytest.raises(RobotError, match="closed"):
        robot.connect()


def test_sawyer_moves_its_hand_to_an_end_effector_target():
    robot = make_robot("sim_sawyer", task="reach-v3", control_hz=20.0, image_size=32)
    with robot:
        first = robot.observe()
        assert first.joint_positions is None and first.frames["corner"].shape == (32, 32, 3)
        target = first.current_target(robot.spec)
        target[0] += 0.1
        robot.act(target)
        assert wait_until(lambda: np.linalg.norm(robot.observe().ee_position - target[:3]) < 0.02)


def test_sawyer_camera_can_stream_a_non_square_frame_and_refuses_a_bad_size():
    """A real camera streams e.g. 480x640 while training uses a resize: ``image_size=[h, w]``."""
    robot = make_robot("sim_sawyer", task="reach-v3", control_hz=20.0, image_size=[24, 40])
    with robot:
        assert robot.spec.cameras[0].height == 24 and robot.spec.cameras[0].width == 40
        assert robot.observe().frames["corner"].shape == (24, 40, 3)
    for bad in ([24], [24, 0], [24.5, 40]):
        with pytest.raises(ValueError, match=r"image_size must be a positive int or \[height, width\]"):
            camera_shape(bad)


def test_so101_reach_success_is_the_gripper_at_the_cube_and_pick_needs_a_lift():
    """``success="reach"``: the cube within REACH_SUCCESS_DISTANCE of the gripper's end point; the
    package's pick criterion (``success="pick"``) also needs the cube lifted from where it started."""
    import mujoco

    from infinirl.realworld.sim_so101 import REACH_SUCCESS_DISTANCE, SO101Plant

    plants = {name: SO101Plant(control_hz=20.0, image_size=None, success=name) for name in ("reach", "pick")}
    try:
        for plant in plants.values():
            plant.reset(seed=0)
            assert plant.read().info["success"] is False  # the cube starts away from the gripper
            env = plant._env
            ee = env.data.sensor("so101/ee_pos").data.copy()
            block = env.model.joint(env.model.body("block").jntadr[0]).qposadr[0]
            env.data.qpos[block:block + 3] = ee + [0.0, 0.0, -0.5 * REACH_SUCCESS_DISTANCE]  # resting under the gripper
            mujoco.mj_forward(env.model, env.data)
        assert plants["reach"].read().info["success"] is True
        assert plants["pick"].read().info["success"] is True  # at the gripper and 0.1 m above its start
        plants["pick"]._block_start_z = float(plants["pick"].read().info["block_position"][2])
        assert plants["pick"].read().info["success"] is False  # the same place, had it started there: no lift
    finally:
        for plant in plants.values():
            plant.close()
    with pytest.raises(ValueError, match="success='grasp'; choose one of pick, reach"):
        make_robot("sim_so101", image_size=None, success="grasp")


def test_lockstep_advances_one_control_period_per_command_whatever_the_wall_clock():
    """``lockstep=True``: ``act`` returns after exactly one tick toward the command and nothing moves
    between commands, so two arms given the same commands at different, irregular paces (late steps)
    report the same states: what makes the robot runners' learning metrics reproducible."""
    def drive(pauses):
        robot = make_robot("sim_sawyer", task="reach-v3", control_hz=50.0, image_size=None, seed=3, lockstep=True)
        states = []
        with robot:
            start = robot.observe()
            target = start.current_target(robot.spec)
            for pause in pauses:
                target[:3] += [0.004, -0.003, 0.002]
                before = robot.observe().tick
                robot.act(target)
                assert robot.observe().tick == before + 1  # exactly one period of simulated time
                time.sleep(pause)  # several periods of wall-clock time: no tick
                assert robot.observe().tick == before + 1
                states.append(robot.observe().info["state"])
            assert robot.stats.late_ticks == 0 and robot.stats.commands_applied == len(pauses)
        return np.array(states)

    steady = drive([0.0] * 6)
    irregular = drive([0.05, 0.0, 0.1, 0.0, 0.07, 0.0])
    np.testing.assert_array_equal(steady, irregular)
    assert np.linalg.norm(steady[-1][:3] - steady[0][:3]) > 0.01  # the hand did move


def test_lockstep_renders_each_ticks_frames_and_refuses_a_latency():
    """A plant with a camera thread (the SO-101) renders on the control thread in lockstep, so each
    observation's frame shows the state after its tick; a command latency has no meaning there."""
    from infinirl.config import ConfigError
    from infinirl.realworld.driver import ROBOT_DRIVERS

    robot = make_robot("sim_so101", control_hz=20.0, image_size=32, lockstep=True)
    with robot:
        frames_before = robot.stats.frames
        target = robot.observe().current_target(robot.spec)
        target[0] += 0.3
        for _ in range(3):
            robot.act(target)
        assert robot.stats.frames == frames_before + 3  # one frame per tick, rendered at the tick
        assert robot.observe().frames["front"].shape == (32, 32, 3)
    for kind in ("sim_so101", "sim_sawyer"):
        with pytest.raises(ValueError, match="lockstep=True .* latency_s=0.1 has no meaning"):
            make_robot(kind, image_size=None, latency_s=0.1, lockstep=True)
        with pytest.raises(ConfigError, match="robot.options: lockstep=True .* set latency_s=0 or lockstep=false"):
            ROBOT_DRIVERS.get(kind).check_options(kind, {"lockstep": True, "latency_s": 0.1}, "robot.options")


def test_first_observation_after_a_reset_shows_the_new_episode_even_with_a_render_in_flight():
    """Real time with a camera thread (the SO-101): a render of the old episode's scene that is still
    in flight when the reset puts the scene back completes after it. Its frames must not become the
    new episode's first observation (nor displace the new scene's capture): ``reset`` returns the
    frame of the scene captured at the reset, beside the state of that same instant."""
    import threading

    from infinirl.realworld.sim_robot import SimulatedRobot
    from infinirl.realworld.sim_so101 import SO101Plant

    class HeldRenderPlant(SO101Plant):
        """The SO-101 scene whose next render, once asked to, stays in flight until released; each
        frame it renders is recorded with the cube position and arm joints of the scene it shows."""

        def __init__(self, **options):
            super().__init__(**options)
            self.hold_next, self.holding, self.release = threading.Event(), threading.Event(), threading.Event()
            self.reset_done, self.captured_after_reset = threading.Event(), threading.Event()
            self.rendered: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (frame, its scene's cube, joints)

        def scene_shown(self, frame):
            return next((cube, joints) for rendered, cube, joints in self.rendered if rendered is frame)

        def reset(self, seed):
            super().reset(seed)
            self.reset_done.set()

        def capture(self):
            if self.reset_done.is_set():
                self.captured_after_reset.set()
            return super().capture()

        def render(self, scene=None):
            frames = super().render(scene)
            self.rendered.append((frames["front"], np.array(scene.sensor("block_pos").data),
                                  np.array(scene.qpos[self._qpos])))
            if self.hold_next.is_set():
                self.hold_next.clear()
                self.holding.set()
                assert self.release.wait(10.0)
            return frames

    plants = []

    def build():
        plants.append(HeldRenderPlant(control_hz=20.0, image_size=32))
        return plants[-1]

    def assert_shows(observation):
        cube, joints = plants[0].scene_shown(observation.frames["front"])
        np.testing.assert_array_equal(cube, observation.info["block_position"])
        np.testing.assert_array_equal(joints, observation.joint_positions)

    robot = SimulatedRobot(build, seed=0)
    with robot:
        plant = plants[0]
        first = robot.observe()
        assert_shows(first)
        plant.hold_next.set()
        assert plant.holding.wait(10.0)  # a frame of episode 0 is being rendered
        # Nothing captures while a render is in flight (one scene copy at a time), so these mark the reset's.
        plant.reset_done.clear()
        plant.captured_after_reset.clear()
        answer = {}
        resetting = threading.Thread(target=lambda: answer.setdefault("obs", robot.reset()))
        resetting.start()
        # The reset has put the scene back and captured it (under the lock the control thread keeps
        # until it waits for the frame): only now does the old render complete.
        assert plant.captured_after_reset.wait(10.0)
        plant.release.set()
        resetting.join(20.0)
        obs = answer["obs"]
        assert not np.allclose(obs.info["block_position"], first.info["block_position"])  # episode 1 moved the cube
        # The frame is of the scene captured at the reset, and the state is of that same instant.
        assert_shows(obs)
        assert robot.stats.stale_frames == 1  # the old episode's frame, dropped when its render completed
