"""The generic gymnasium adapter on a discrete classic-control task and a MuJoCo task."""

import os

import numpy as np
import pytest

from infinirl.envs import make_env

gym = pytest.importorskip("gymnasium")


def test_cartpole_matches_gymnasium_with_the_same_seed():
    reference = gym.make("CartPole-v1")
    expected_obs, _ = reference.reset(seed=3)
    with make_env("gym:CartPole-v1", 2, num_workers=0) as env:
        assert env.action_space.num_choices == 2
        obs = env.reset(seeds=[3, 4])
        np.testing.assert_array_equal(obs["state"][0], expected_obs)
        assert obs["state"].dtype == np.float32
        result = env.step(np.array([1, 0]))
        expected_next, reward, *_ = reference.step(1)
        np.testing.assert_allclose(result.obs["state"][0], expected_next, rtol=1e-6)
        assert result.reward[0] == reward


def test_cartpole_episode_ends_and_auto_resets():
    with make_env("gym:CartPole-v1", 1, num_workers=0) as env:
        env.reset(seeds=0)
        for _ in range(500):
            result = env.step(np.array([0]))  # always push left: falls within ~10 steps
            if result.done[0]:
                break
        assert result.terminated[0]
        assert np.abs(result.info["final_obs"]["state"][0, 2]) > 0.2  # the pole fell
        assert np.abs(result.obs["state"][0]).max() < 0.06  # fresh reset state
        assert 5 <= result.info["episode_length"][0] < 30


def test_mujoco_task_clips_actions_and_renders_rgb():
    pytest.importorskip("mujoco")
    with make_env("gym:InvertedPendulum-v5", 2, num_workers=0, obs_mode="state+rgb",
                  width=64, height=48) as env:
        assert env.action_space.shape == (1,) and env.action_space.high[0] == 3.0
        assert env.observation_spec["rgb"].shape == (48, 64, 3)
        env.reset(seeds=[0, 0])
        big = env.step(np.array([[100.0], [3.0]], np.float32))  # 100 is clipped to 3
        np.testing.assert_allclose(big.obs["state"][0], big.obs["state"][1])
        assert big.obs["rgb"].shape == (2, 48, 64, 3) and big.obs["rgb"].dtype == np.uint8
        assert big.obs["rgb"].std() > 10  # a real picture, not a blank buffer


def test_unobserved_steps_repeat_the_frame_and_episode_ends_render():
    pytest.importorskip("mujoco")
    from infinirl.envs.gymnasium_env import GymnasiumSubEnv

    kwargs = dict(obs_mode="state+rgb", make_kwargs={"width": 64, "height": 48})
    full, skipping = GymnasiumSubEnv("InvertedPendulum-v5", **kwargs), GymnasiumSubEnv("InvertedPendulum-v5", **kwargs)
    try:
        full.reset(seed=0)
        first = skipping.reset(seed=0)["rgb"]
        for _ in range(100):  # pushed one way, the pole falls within a few dozen steps
            a, b = full.step(np.array([3.0], np.float32)), skipping.step(np.array([3.0], np.float32), observe=False)
            np.testing.assert_array_equal(a.obs["state"], b.obs["state"])
            if b.terminated:
                break
            np.testing.assert_array_equal(b.obs["rgb"], first)  # nobody reads it: not drawn
        assert b.terminated
        np.testing.assert_array_equal(a.obs["rgb"], b.obs["rgb"])  # the final frame is drawn
        assert not np.array_equal(b.obs["rgb"], first)
    finally:
        full.close()
        skipping.close()


def test_headless_gl_renders_software_frames_on_the_calling_thread(monkeypatch):
    """osmesa gets LP_NUM_THREADS=0 (llvmpipe rasterises on the calling thread) unless the user
    chose a value; other backends are left alone."""
    from infinirl.envs.gymnasium_env import use_headless_gl

    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    monkeypatch.setenv("MUJOCO_GL", "egl")
    assert use_headless_gl() == "egl" and "LP_NUM_THREADS" not in os.environ
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert use_headless_gl() == "osmesa" and os.environ["LP_NUM_THREADS"] == "0"
    monkeypatch.setenv("LP_NUM_THREADS", "4")
    use_headless_gl()
    assert os.environ["LP_NUM_THREADS"] == "4"
