"""A robot as an environment: action mapping, pacing, rewards and episode ends on simulated robots."""

import time

import numpy as np
import pytest

from infinirl.realworld.driver import make_robot
from infinirl.realworld.robot_env import REWARDS, RobotEnv, RobotEnvSpec, action_to_command, max_target_step
from infinirl.realworld.safety import SafeRobot, SafetyConfig

# The safety deadlines have tests of their own; here a loaded machine must not stop the robot mid-test.
NO_DEADLINES = SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None)


def test_action_to_command_matches_a_float64_reference():
    spec = make_robot("sim_sawyer", image_size=None).spec  # not connected: the spec alone
    max_step = max_target_step(spec, SafetyConfig())
    rng = np.random.default_rng(0)
    reference = np.array([0.0, 0.6, 0.2, 0.5])
    for _ in range(20):
        action = rng.uniform(-1.5, 1.5, 4)
        clipped = np.clip(action, -1, 1)
        expected_abs = [float(lo) + (float(a) + 1) / 2 * (float(hi) - float(lo))
                        for a, lo, hi in zip(clipped, spec.action_low, spec.action_high)]
        np.testing.assert_allclose(action_to_command(action, reference, spec, "absolute", max_step), expected_abs)
        delta = action_to_command(action, reference, spec, "delta", max_step)
        for i in range(3):
            want = min(max(reference[i] + clipped[i] * max_step[i], spec.action_low[i]), spec.action_high[i])
            assert delta[i] == pytest.approx(want)
        assert delta[3] == pytest.approx(expected_abs[3])  # the gripper is absolute in both modes
    with pytest.raises(ValueError, match="4 entries"):
        action_to_command(np.zeros(3), reference, spec, "delta", max_step)


def test_spec_refuses_unknown_names_listing_the_registered_ones():
    with pytest.raises(KeyError, match="goal_distance"):
        RobotEnvSpec(rewards={"goal_distanc": 1.0})
    with pytest.raises(KeyError, match="proprio"):
        RobotEnvSpec(observations=("propio",))


def test_sawyer_reach_episode_ends_on_success_at_the_robots_pace():
    robot = SafeRobot(make_robot("sim_sawyer", control_hz=20.0, image_size=None), NO_DEADLINES)
    robot.connect()
    try:
        env = RobotEnv(robot, RobotEnvSpec(observations=("proprio", "sim_state"),
                                           rewards={"goal_distance": 1.0, "success": 1.0}, max_episode_steps=60))
        obs = env.reset()
        assert obs["state"].dtype == np.float32 and obs["state"].shape == (env.observation_size(),)
        started, steps = time.monotonic(), 0
        while True:  # a scripted reach: straight to the goal (the last three state entries)
            state = obs["state"]
            step = env.step(np.append(np.clip((state[-3:] - state[:3]) / env.max_step, -1, 1), 1.0))
            obs, steps = step.obs, steps + 1
            if step.terminated or step.truncated:
                break
        assert step.success and step.terminated and not step.truncated
        assert time.monotonic() - started >= (steps - 1) / 20.0  # one control period per step, never faster
        reward = REWARDS.get("goal_distance").reward(robot.observe()) + 1.0
        assert step.reward == pytest.approx(reward, abs=0.05)  # the hand moves on a little after the step
        env.reset()
        for _ in range(3):
            step = env.step(np.zeros(4))
        assert env.steps == 3 and not step.terminated

        with_action = RobotEnv(robot, RobotEnvSpec(observations=("proprio", "last_action")))
        assert np.all(with_action.reset()["state"][4:] == 0)
        step = with_action.step(np.array([0.5, -2.0, 0.0, 1.0]))
        np.testing.assert_allclose(step.obs["state"][4:], [0.5, -1.0, 0.0, 1.0])  # as applied: clipped to [-1, 1]
    finally:
        robot.close()


def test_step_limit_truncates_and_so101_gives_pixels():
    robot = SafeRobot(make_robot("sim_so101", control_hz=20.0, image_size=32), NO_DEADLINES)
    robot.connect()
    try:
        env = RobotEnv(robot, RobotEnvSpec(observations=("proprio", "block_position"), cameras=("front",),
                                           rewards={"block_distance": 1.0, "success": 10.0}, max_episode_steps=4))
        obs = env.reset()
        assert obs["pixels.front"].shape == (32, 32, 3) and obs["state"].shape == (9,)
        results = [env.step(np.zeros(6)) for _ in range(4)]
        assert [r.truncated for r in results] == [False, False, False, True]
        assert all(r.reward < 0 for r in results)
        with pytest.raises(ValueError, match="no \\['wrist'\\]"):
            RobotEnv(robot, RobotEnvSpec(cameras=("wrist",)))
    finally:
        robot.close()


def test_frames_are_resized_to_the_training_resolution_at_the_robot():
    """A camera streaming more pixels than training uses (``image_size=[h, w]``) with
    ``frame_size``: the observation, and so the policy, the replay store and the link, carries the
    resized frame; the raw one stays with the robot."""
    robot = SafeRobot(make_robot("sim_sawyer", control_hz=20.0, image_size=[48, 64]), NO_DEADLINES)
    robot.connect()
    try:
        env = RobotEnv(robot, RobotEnvSpec(cameras=("corner",), frame_size=[16, 24], max_episode_steps=2))
        obs = env.reset()
        assert obs["pixels.corner"].shape == (16, 24, 3) and obs["pixels.corner"].dtype == np.uint8
        assert env.observation_shapes()["pixels.corner"] == (16, 24, 3)
        assert env.camera_shapes() == {"corner": (16, 24)}  # what the policy's encoder is built for
        assert env.step(np.zeros(4)).obs["pixels.corner"].shape == (16, 24, 3)
        observation = robot.observe()
        raw = observation.frames["corner"]
        assert raw.shape == (48, 64, 3)
        from PIL import Image
        expected = np.asarray(Image.fromarray(raw).resize((24, 16), Image.BILINEAR))
        np.testing.assert_array_equal(env._obs(observation)["pixels.corner"], expected)
        assert RobotEnv(robot, RobotEnvSpec(cameras=("corner",))).reset()["pixels.corner"].shape == (48, 64, 3)
    finally:
        robot.close()
    for bad in ([16], [16, 0], [16.0, 24]):
        with pytest.raises(ValueError, match="frame_size must be \\[height, width\\]"):
            RobotEnvSpec(frame_size=bad)



def test_camera_names_rename_a_robots_camera_in_the_observations():
    """Robots of a fleet with different cameras give them one name (and one frame size)."""
    robot = SafeRobot(make_robot("sim_sawyer", control_hz=20.0, image_size=32), NO_DEADLINES)
    robot.connect()
    try:
        env = RobotEnv(robot, RobotEnvSpec(cameras=("corner",), camera_names={"corner": "main"}, frame_size=[16, 16]))
        assert set(env.reset()) == {"state", "pixels.main"} and env.camera_shapes() == {"main": (16, 16)}
    finally:
        robot.close()
    with pytest.raises(ValueError, match="renames \\['wrist'\\], which are not among the cameras"):
        RobotEnvSpec(cameras=("corner",), camera_names={"wrist": "main"})
    with pytest.raises(ValueError, match="gives two cameras one name"):
        RobotEnvSpec(cameras=("corner", "wrist"), camera_names={"wrist": "corner"})
