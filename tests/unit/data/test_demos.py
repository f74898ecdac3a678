"""Scripted experts and `infinirl demos`: MetaWorld's expert solves our env, the command writes a
dataset our reader (and so LeRobot's layout) holds, bad arguments get one line."""

import numpy as np
import pytest

pytest.importorskip("metaworld")
pytest.importorskip("imageio_ffmpeg")
pytest.importorskip("pyarrow")

from infinirl.cli import main  # noqa: E402
from infinirl.data.demos import (  # noqa: E402
    METAWORLD_CAMERAS,
    METAWORLD_FPS,
    METAWORLD_INSTRUCTIONS,
    METAWORLD_STATE_NAMES,
    record_episode,
    record_policy_episodes,
    resolve_metaworld_tasks,
)
from infinirl.data.lerobot_dataset import LeRobotDatasetReader  # noqa: E402
from infinirl.envs import make_env  # noqa: E402
from infinirl.envs.experts import EXPERTS, make_expert, metaworld_expert_tasks  # noqa: E402
from infinirl.models.policies.base import PolicyStep  # noqa: E402


class ExpertChunkPolicy:
    """MetaWorld's scripted expert behind the policy interface: a batch of observations in, a chunk
    of ``chunk`` actions per env out (the expert's action for the observation, repeated)."""

    def __init__(self, task: str, chunk: int = 1):
        self.expert, self.chunk, self.calls, self.batch_sizes = make_expert("metaworld", task), chunk, 0, []

    def act(self, obs, deterministic=False):
        import torch

        self.calls += 1
        self.batch_sizes.append(len(obs["state"]))
        rows = [{"state": np.asarray(state)} for state in obs["state"]]
        actions = np.stack([self.expert.act(row) for row in rows])
        return PolicyStep(actions=torch.as_tensor(np.repeat(actions[:, None], self.chunk, axis=1)),
                          logprobs=torch.zeros(len(rows)))


def test_metaworld_expert_succeeds_on_reach_from_our_state_observation():
    expert = make_expert("metaworld", "reach-v3")
    with make_env("metaworld:reach-v3", 1, num_workers=0, terminate_on_success=True) as env:
        obs = env.reset(seeds=[3])
        steps = 0
        while steps < 200:
            steps += 1
            action = expert.act({key: value[0] for key, value in obs.items()})
            assert action.dtype == np.float32 and action.shape == (4,)
            assert np.all(np.abs(action) <= 1.0), "clipped to MetaWorld's action space"
            result = env.step(action[None], autoreset=False)
            obs = result.obs
            if result.done[0]:
                break
        assert result.info["success"][0], f"the expert did not reach the goal in {steps} steps"
        assert steps < 120


def test_every_metaworld_task_has_an_expert_and_noise_is_seeded():
    from infinirl.envs.metaworld_env import metaworld_task_names

    v3_tasks = {name for name, tasks in metaworld_task_names().items() if tasks == [name]}
    assert v3_tasks == set(metaworld_expert_tasks())
    assert "metaworld" in EXPERTS
    state = np.linspace(-0.5, 0.5, 39, dtype=np.float32)
    clean = make_expert("metaworld", "push-v3").act({"state": state})
    noisy = [make_expert("metaworld", "push-v3", noise_std=0.3, seed=7).act({"state": state}) for _ in range(2)]
    np.testing.assert_array_equal(noisy[0], noisy[1])
    assert not np.array_equal(noisy[0], clean) and np.all(np.abs(noisy[0]) <= 1.0)
    with pytest.raises(ValueError, match="no scripted MetaWorld expert for task 'reach-v9'"):
        make_expert("metaworld", "reach-v9")
    with pytest.raises(ValueError, match="unknown scripted expert family 'metaworlds'"):
        make_expert("metaworlds", "reach-v3")


def test_metaworld_tables_match_the_simulator():
    from infinirl.envs.metaworld_env import MetaWorldSubEnv

    assert resolve_metaworld_tasks("MT10") == tuple(METAWORLD_INSTRUCTIONS)
    assert resolve_metaworld_tasks("reach-v3, push-v3,reach-v3") == ("reach-v3", "push-v3")
    env = MetaWorldSubEnv("reach-v3")
    try:
        assert METAWORLD_FPS == round(1.0 / env._sim.dt)  # the rate the dataset's timestamps claim
        assert len(METAWORLD_STATE_NAMES) == env.observation_spec["state"].shape[0] == 39
        model = env._sim.model
        assert METAWORLD_CAMERAS == tuple(model.camera(i).name for i in range(model.ncam))
    finally:
        env.close()


def test_demos_command_writes_a_dataset_of_successful_expert_episodes(tmp_path, capsys):
    out = tmp_path / "reach"
    code = main(["demos", "metaworld", "--tasks", "reach-v3", "--episodes-per-task", "1", "--image-size", "32",
                 "--out", str(out), "--seed", "5", "--no-progress"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "wrote 1 episodes" in printed and str(out) in printed
    assert "reach-v3: expert success 1/1 = 100%" in printed

    reader = LeRobotDatasetReader(out)
    assert reader.num_episodes == 1 and reader.fps == METAWORLD_FPS and reader.tasks == ["reach"]
    episode = reader.episode(0)
    length = len(episode["action"])
    assert f"{length} frames" in printed
    assert episode["observation.images.corner"].shape == (length, 32, 32, 3)
    np.testing.assert_array_equal(episode["observation.state"], episode["observation.environment_state"][:, :4])
    assert episode["next.success"][-1] and not episode["next.success"][:-1].any(), "ends at the first success"
    assert episode["next.done"].tolist() == [False] * (length - 1) + [True]
    assert np.all(np.abs(episode["action"]) <= 1.0)


def test_demos_command_refuses_bad_arguments_in_one_line(tmp_path, capsys):
    def error(*args):
        code = main(["demos", *args, "--no-progress"])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1, err
        return err

    base = ["--episodes-per-task", "1", "--out", str(tmp_path / "x")]
    assert "unknown MetaWorld task 'reach-v9'" in error("metaworld", "--tasks", "reach-v9", *base)
    assert "unknown demonstration source 'metaworlds'" in error("metaworlds", "--tasks", "reach-v3", *base)
    assert "unknown MetaWorld camera 'nope'" in error("metaworld", "--tasks", "reach-v3", "--camera", "nope", *base)
    assert "image_size must be even" in error("metaworld", "--tasks", "reach-v3", "--image-size", "33", *base)
    assert "'natural' has sentences for the MT10 tasks only" in error(
        "metaworld", "--tasks", "reach-wall-v3", "--instructions", "natural", *base)
    (tmp_path / "taken").mkdir()
    assert "already exists" in error("metaworld", "--tasks", "reach-v3", "--episodes-per-task", "1",
                                     "--out", str(tmp_path / "taken"))
    assert not (tmp_path / "x").exists()


def test_batched_policy_recording_equals_one_env_recording():
    seeds = [11, 12, 13]
    key = "observation.images.corner"
    kwargs = dict(num_workers=0, obs_mode="state+rgb", camera="corner", image_size=16, terminate_on_success=True)
    policy = ExpertChunkPolicy("reach-v3")
    with make_env("metaworld:reach-v3", 2, **kwargs) as env:
        batched = record_policy_episodes(env, policy, seeds, key)
    with make_env("metaworld:reach-v3", 1, **kwargs) as env:
        single = [record_episode(env, make_expert("metaworld", "reach-v3"), seed, key) for seed in seeds]
    assert [success for _, success in batched] == [success for _, success, _ in single] == [True] * 3
    lengths = [len(frames["action"]) for frames, _ in batched]
    assert len(set(lengths[:2])) == 2, "the two envs of the first round end at different steps"
    for (frames, _), (expected, _, _) in zip(batched, single, strict=True):
        assert frames.keys() == expected.keys()
        for name in frames:
            np.testing.assert_array_equal(frames[name], expected[name], err_msg=name)
        assert frames["next.done"][-1] and not frames["next.done"][:-1].any()
    first_round = max(lengths[:2])
    assert policy.batch_sizes[:first_round] == [2] * min(lengths[:2]) + [1] * (first_round - min(lengths[:2]))


def test_policy_recording_plans_once_per_chunk_for_the_whole_batch():
    policy = ExpertChunkPolicy("reach-v3", chunk=4)
    with make_env("metaworld:reach-v3", 3, num_workers=0, obs_mode="state+rgb", image_size=16,
                  terminate_on_success=True, max_episode_steps=10) as env:
        episodes = record_policy_episodes(env, policy, [1, 2, 3], "observation.images.corner")
    assert policy.calls == 3  # 10 steps of every env, planned at steps 0, 4 and 8
    for frames, success in episodes:
        assert len(frames["action"]) == 10 and not success
        np.testing.assert_array_equal(frames["action"][0], frames["action"][3])  # one chunk's actions
