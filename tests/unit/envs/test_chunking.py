"""Action chunks: K actions per call, chunk-level reward/done, envs stop at their episode end."""

import numpy as np
import pytest

from infinirl.envs import ActionChunkEnv, VectorEnv
from tests.unit.envs.toy_envs import CounterFactory


def _chunk_env(num_envs=2, chunk_size=4, episode_length=6):
    factory = CounterFactory(episode_length=episode_length, success_at=2)
    return ActionChunkEnv(VectorEnv(factory, num_envs, num_workers=0), chunk_size)


def test_chunk_sums_rewards_and_runs_all_steps_when_no_episode_ends():
    with _chunk_env() as env:
        env.reset(seeds=0)
        actions = np.zeros((2, 4, 2), np.float32)
        actions[:, :, 0] = [[0.1, 0.2, 0.3, 0.4], [1.0, 1.0, 1.0, -1.0]]
        result = env.step(actions)
        np.testing.assert_allclose(result.reward, [1.0, 2.0], rtol=1e-6)
        np.testing.assert_allclose(result.info["step_rewards"], actions[:, :, 0])
        assert result.info["step_mask"].all() and not result.done.any()
        np.testing.assert_array_equal(result.obs["state"][:, 1], [4, 4])
        assert result.info["success"].all()  # success (t >= 2) at some step of the chunk


def test_env_whose_episode_ends_mid_chunk_ignores_the_rest_of_its_chunk():
    with _chunk_env(episode_length=6) as env:
        env.reset(seeds=0)
        env.step(np.ones((2, 4, 2), np.float32))  # t = 4 for both
        env.env.step(np.ones((2, 2), np.float32), env_mask=np.array([True, False]))  # env 0: t = 5
        result = env.step(np.ones((2, 4, 2), np.float32))
        # env 0 ends after 1 step of the chunk, env 1 after 2; neither runs the rest
        np.testing.assert_array_equal(result.info["step_mask"], [[1, 0, 0, 0], [1, 1, 0, 0]])
        np.testing.assert_array_equal(result.reward, [1, 2])
        assert result.terminated.all()
        np.testing.assert_array_equal(result.info["final_obs"]["state"][:, 1], [6, 6])
        np.testing.assert_array_equal(result.info["episode_return"], [6, 6])
        # the new episodes have not been stepped by leftover actions
        np.testing.assert_array_equal(result.obs["state"][:, 1], [0, 0])


def test_chunk_without_autoreset_ends_episodes_in_place():
    with _chunk_env(episode_length=6) as env:
        env.reset(seeds=0)
        env.step(np.ones((2, 4, 2), np.float32))  # t = 4
        result = env.step(np.ones((2, 4, 2), np.float32), autoreset=False)
        np.testing.assert_array_equal(result.info["step_mask"], [[1, 1, 0, 0], [1, 1, 0, 0]])
        assert result.terminated.all()
        np.testing.assert_array_equal(result.obs["state"][:, 1], [6, 6])  # the final obs, no new episode
        np.testing.assert_array_equal(result.info["final_obs"]["state"], result.obs["state"])
        with pytest.raises(RuntimeError, match="reset"):
            env.step(np.ones((2, 4, 2), np.float32))
        env.reset(seeds=0)
        assert not env.step(np.ones((2, 4, 2), np.float32)).done.any()


def test_chunk_action_shape_is_checked():
    with _chunk_env(chunk_size=3) as env:
        env.reset()
        assert env.action_space.shape == (3, 2)
        with pytest.raises(ValueError, match=r"expected actions of shape \(2, 3, 2\)"):
            env.step(np.zeros((2, 4, 2)))


def _framed_chunk_env(skip_inner_frames, episode_length=6, max_episode_steps=None, num_workers=0):
    from tests.unit.envs.toy_envs import FramedCounterFactory

    factory = FramedCounterFactory(episode_length=episode_length)
    vector = VectorEnv(factory, 2, num_workers=num_workers, max_episode_steps=max_episode_steps)
    return ActionChunkEnv(vector, 4, skip_inner_frames=skip_inner_frames)


def _rollout(env, chunks):
    """Observations, rewards, ends and final observations of ``chunks`` chunks of unit actions."""
    trace = [env.reset(seeds=0)]
    for _ in range(chunks):
        result = env.step(np.ones((2, 4, 2), np.float32))
        trace.append((result.obs, result.reward, result.done, result.info["final_obs"],
                      result.info["final_obs_mask"]))
    return trace


@pytest.mark.parametrize("num_workers", [0, 1])
def test_inner_steps_of_a_chunk_render_no_frame(num_workers):
    # 6-step episodes in chunks of 4: the frames a policy or a bootstrap reads (a chunk's last
    # step, an episode's last step, a reset) are drawn; the inner steps' are not
    with _framed_chunk_env(True, num_workers=num_workers) as env:
        env.reset(seeds=0)
        result = env.step(np.ones((2, 4, 2), np.float32))  # t = 1..4: only t = 4 rendered
        np.testing.assert_array_equal(result.obs["frame"][:, 0], [4, 4])
        np.testing.assert_array_equal(result.obs["renders"][:, 0], [2, 2])  # reset + t = 4
        result = env.step(np.ones((2, 4, 2), np.float32))  # t = 5, 6 (ends), then a reset
        np.testing.assert_array_equal(result.info["final_obs"]["frame"][:, 0], [6, 6])
        np.testing.assert_array_equal(result.obs["frame"][:, 0], [0, 0])
        np.testing.assert_array_equal(result.obs["renders"][:, 0], [4, 4])  # + t = 6 + reset


def test_skipping_inner_frames_changes_nothing_a_caller_reads():
    for max_steps in (None, 5):  # episodes end by the env itself, or by the vectoriser's time limit
        with _framed_chunk_env(True, max_episode_steps=max_steps) as skip, \
                _framed_chunk_env(False, max_episode_steps=max_steps) as full:
            for a, b in zip(_rollout(skip, 5)[1:], _rollout(full, 5)[1:], strict=True):
                obs_a, obs_b = a[0], b[0]
                for key in ("state", "frame"):
                    np.testing.assert_array_equal(obs_a[key], obs_b[key])
                np.testing.assert_array_equal(a[1], b[1])
                np.testing.assert_array_equal(a[2], b[2])
                ended = a[4]
                np.testing.assert_array_equal(a[3]["frame"][ended], b[3]["frame"][ended])
            assert (obs_a["renders"] < obs_b["renders"]).all()  # and it drew fewer frames
