"""MetaWorld adapter: seeded resets, fixed states, success, 200-step episodes, upright images."""

import numpy as np
import pytest

from infinirl.envs import make_env

pytest.importorskip("metaworld")


def _reach_towards_goal(state: np.ndarray) -> np.ndarray:
    """Scripted reach policy: move the hand (state[:3]) to the goal (state[-3:])."""
    actions = np.zeros((len(state), 4), np.float32)
    actions[:, :3] = np.clip((state[:, -3:] - state[:, :3]) * 10.0, -1.0, 1.0)
    return actions


def test_same_seed_gives_identical_first_obs_and_seeds_differ():
    with make_env("metaworld:reach-v3", 3, num_workers=0) as env:
        first = env.reset(seeds=[11, 11, 12])["state"]
        np.testing.assert_array_equal(first[0], first[1])
        assert not np.allclose(first[0, -3:], first[2, -3:])  # another seed, another goal
        env.step(env.action_space.sample(3))
        again = env.reset(seeds=[11, 11, 12])["state"]
        np.testing.assert_array_equal(again, first)
        assert env.observation_spec["state"].shape == (39,)
        np.testing.assert_array_equal(env.reset(seeds=[11, 0, 0])["proprio"][0], first[0, :4])


def test_state_ids_give_a_group_one_task_and_the_scripted_policy_solves_it():
    with make_env("metaworld:reach-v3", 4, num_workers=0) as env:
        obs = env.reset(state_ids=[5, 5, 6, 6])
        state = obs["state"]
        np.testing.assert_array_equal(state[0], state[1])
        np.testing.assert_array_equal(state[2], state[3])
        assert not np.allclose(state[0, -3:], state[2, -3:])
        assert obs["instruction"] == ["reach"] * 4
        successes = []
        for step in range(200):
            result = env.step(_reach_towards_goal(obs["state"]))
            obs = result.obs
            successes.append(result.info["success"])
            if step < 199:
                assert not result.done.any()
        assert result.truncated.all() and not result.terminated.any()  # 200-step episodes
        np.testing.assert_array_equal(result.info["episode_length"], [200] * 4)
        assert result.info["episode_success"].all() and np.any(successes, axis=0).all()
        returns = result.info["episode_return"]
        assert returns[0] == returns[1] and returns[2] == returns[3]  # same state, same actions
        assert not np.array_equal(obs["state"][:, -3:], state[:, -3:])  # auto-reset: new tasks


def test_terminate_on_success_ends_the_episode():
    with make_env("metaworld:reach-v3", 1, num_workers=0, terminate_on_success=True) as env:
        obs = env.reset(seeds=1)
        for _ in range(200):
            result = env.step(_reach_towards_goal(obs["state"]))
            obs = result.obs
            if result.done[0]:
                break
        assert result.terminated[0] and result.info["success"][0]
        assert result.info["episode_length"][0] < 200



@pytest.mark.parametrize("limit", [7, 230])
def test_the_configured_time_limit_is_the_episode_length_above_metaworlds_200_too(limit):
    """make_env's max_episode_steps reaches MetaWorld's own limit: 230 is not cut at its default 200."""
    with make_env("metaworld:reach-v3", 1, num_workers=0, max_episode_steps=limit) as env:
        env.reset(seeds=[3])
        steps, done = 0, False
        while not done:
            result = env.step(np.zeros((1, 4), np.float32))
            steps, done = steps + 1, bool(result.done[0])
        assert steps == limit and bool(result.truncated[0]) and not bool(result.terminated[0])


def test_sparse_reward_is_the_success_signal_and_dense_is_metaworlds():
    """``reward_mode="sparse"``: 1 on a step where the task is solved, 0 elsewhere; the physics and
    the success flags are those of the dense env stepped with the same actions; ``success_bonus``
    adds its value to the dense reward on exactly the solved steps."""
    kinds = {}
    for mode, bonus in (("dense", 0.0), ("sparse", 0.0), ("dense_bonus", 10.0)):
        with make_env("metaworld:reach-v3", 1, num_workers=0, reward_mode=mode.split("_")[0],
                      success_bonus=bonus) as env:
            obs = env.reset(seeds=1)
            rewards, successes, states = [], [], []
            for _ in range(60):
                result = env.step(_reach_towards_goal(obs["state"]))
                obs = result.obs
                rewards.append(float(result.reward[0]))
                successes.append(bool(result.info["success"][0]))
                states.append(obs["state"][0])
            kinds[mode] = (np.array(rewards), np.array(successes), np.array(states))
    dense, sparse = kinds["dense"], kinds["sparse"]
    np.testing.assert_array_equal(sparse[1], dense[1])
    np.testing.assert_array_equal(sparse[2], dense[2])
    assert sparse[1].any() and not sparse[1].all()  # solved part of the way in
    np.testing.assert_array_equal(sparse[0], sparse[1].astype(float))
    assert (dense[0][~dense[1]] > 0).any()  # MetaWorld's shaped reward pays before success
    bonus = kinds["dense_bonus"]
    np.testing.assert_array_equal(bonus[2], dense[2])
    np.testing.assert_allclose(bonus[0], dense[0] + 10.0 * dense[1])


def test_a_negative_success_bonus_is_refused():
    with pytest.raises(ValueError, match="success_bonus"):
        make_env("metaworld:reach-v3", 1, num_workers=0, success_bonus=-1.0)


def test_unknown_reward_mode_is_refused():
    with pytest.raises(ValueError, match="reward_mode"):
        make_env("metaworld:reach-v3", 1, num_workers=0, reward_mode="shaped")

def test_camera_frames_are_upright():
    """In an upright view of the ``corner`` camera the wooden table is below the red robot arm.

    The raw MuJoCo frame of this camera is upside down (the camera is mounted rolled by 180°),
    so the same check on the un-rotated frame fails: that is what the adapter fixes.
    """
    with make_env("metaworld:reach-v3", 1, num_workers=0, obs_mode="state+rgb",
                  image_size=96) as env:
        frame = env.reset(seeds=0)["rgb"][0]
        assert frame.shape == (96, 96, 3) and frame.dtype == np.uint8
        assert _table_row(frame) > _arm_row(frame) + 10
        raw = frame[::-1, ::-1]
        assert _table_row(raw) < _arm_row(raw) - 10
        np.testing.assert_array_equal(env.render()[0], frame)


def test_rgb_alone_observes_no_privileged_state():
    """obs_mode="rgb": the camera frame, the robot's own proprio and the instruction, not the
    39-float state with the objects' and goal's poses, in the spec and in every observation."""
    with make_env("metaworld:reach-v3", 1, num_workers=0, obs_mode="rgb", image_size=32) as pixels, \
            make_env("metaworld:reach-v3", 1, num_workers=0, obs_mode="state+rgb", image_size=32) as both:
        assert list(pixels.observation_spec) == ["proprio", "rgb", "instruction"]
        assert list(both.observation_spec) == ["state", "proprio", "rgb", "instruction"]
        obs, full = pixels.reset(seeds=3), both.reset(seeds=3)
        assert set(obs) == {"proprio", "rgb", "instruction"}
        np.testing.assert_array_equal(obs["proprio"], full["proprio"])
        np.testing.assert_array_equal(obs["rgb"], full["rgb"])
        action = np.full((1, 4), 0.5, np.float32)
        result = pixels.step(action)
        assert set(result.obs) == {"proprio", "rgb", "instruction"}
        np.testing.assert_array_equal(result.obs["proprio"], both.step(action).obs["proprio"])


def test_fast_render_changes_visual_settings_only():
    """fast_render: no shadows, reflections or multisampling (the costly software-GL passes); the
    physics, hence every state observation, is the same as with the model's own visuals."""
    from infinirl.envs.metaworld_env import MetaWorldSubEnv

    fast = MetaWorldSubEnv("reach-v3", obs_mode="state+rgb", image_size=32)
    plain = MetaWorldSubEnv("reach-v3", obs_mode="state+rgb", image_size=32, fast_render=False)
    try:
        visuals = fast._sim.model.vis.quality
        assert visuals.offsamples == 0 and plain._sim.model.vis.quality.offsamples > 0
        assert not fast._sim.model.light_castshadow.any() and plain._sim.model.light_castshadow.any()
        first_fast, first_plain = fast.reset(seed=5), plain.reset(seed=5)
        np.testing.assert_array_equal(first_fast["state"], first_plain["state"])
        action = np.array([0.5, -0.3, 0.2, 0.0], np.float32)
        for _ in range(5):
            np.testing.assert_array_equal(fast.step(action).obs["state"], plain.step(action).obs["state"])
        assert fast.render().shape == plain.render().shape == (32, 32, 3)
    finally:
        fast.close()
        plain.close()


def _table_row(frame: np.ndarray) -> float:
    r, g, b = (frame[..., c].astype(int) for c in range(3))
    wood = (r - b > 35) & (g - b > 15) & (r - g < 70)  # brown: red > green > blue, not saturated
    return float(np.nonzero(wood)[0].mean())


def _arm_row(frame: np.ndarray) -> float:
    r, g = frame[..., 0].astype(int), frame[..., 1].astype(int)
    return float(np.nonzero(r - g > 80)[0].mean())  # saturated red: the Sawyer arm


def test_mt10_gives_each_env_its_own_task():
    with make_env("metaworld:MT10", 3, num_workers=0) as env:
        obs = env.reset(seeds=0)
        assert len(set(obs["instruction"])) == 3 and obs["instruction"][0] == "reach"


def test_worker_processes_match_in_process_stepping():
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (2, 4)).astype(np.float32) for _ in range(5)]
    states = []
    for num_workers in (0, 2):
        with make_env("metaworld:push-v3", 2, num_workers=num_workers) as env:
            env.reset(seeds=[3, 4])
            states.append([env.step(a).obs["state"] for a in actions])
    np.testing.assert_array_equal(np.stack(states[0]), np.stack(states[1]))


def test_action_chunks_skip_inner_frames_without_changing_what_is_read():
    # chunks of 4 in 10-step episodes: each chunk's last frame and the final frames of ended
    # episodes are the ones rendered at every step; state, reward and success are untouched
    from infinirl.envs import ActionChunkEnv, VectorEnv
    from infinirl.envs.metaworld_env import MetaWorldFactory

    rng = np.random.default_rng(0)
    chunks = [rng.uniform(-1, 1, (2, 4, 4)).astype(np.float32) for _ in range(6)]
    traces = []
    for skip in (True, False):
        factory = MetaWorldFactory(("door-open-v3",), obs_mode="state+rgb", image_size=32, max_episode_steps=10)
        with ActionChunkEnv(VectorEnv(factory, 2, num_workers=0), 4, skip_inner_frames=skip) as env:
            env.reset(seeds=[5, 6])
            results = [env.step(chunk) for chunk in chunks]
        traces.append(results)
    for a, b in zip(*traces, strict=True):
        for key in ("state", "rgb"):
            np.testing.assert_array_equal(a.obs[key], b.obs[key])
        np.testing.assert_array_equal(a.reward, b.reward)
        np.testing.assert_array_equal(a.info["success"], b.info["success"])
        np.testing.assert_array_equal(a.done, b.done)
        ended = a.info["final_obs_mask"]
        np.testing.assert_array_equal(a.info["final_obs"]["rgb"][ended], b.info["final_obs"]["rgb"][ended])
    assert any(result.done.any() for result in traces[0])
