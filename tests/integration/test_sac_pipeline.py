"""The SAC runner end to end on InvertedPendulum-v5 (MuJoCo, fast): collector and learner as
components, replay buffer, weight sync, eval, video, checkpoints; and exact resume: 4 iterations
straight and the same run resumed from iteration 3 give the same weights, the same replay buffer and the same metrics,
with collection and learning alternating or pipelined (collect_ahead).

Episodes deliberately span iteration boundaries (2 envs, 40 steps per iteration), the buffer wraps
around (capacity 100 < 320 transitions) and the warm-up ends inside an iteration, so the resumed
collector has to replay its envs' current episodes and continue every generator exactly."""

import json

import pytest

pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.runners.sac import run  # noqa: E402
from infinirl.runners.sac_config import SACConfig  # noqa: E402
from tests.integration.pins import check_pinned  # noqa: E402
from tests.integration.resume import killed_after_checkpoint  # noqa: E402


def make_cfg(output_dir, iterations, **extra):
    raw = {
        "iterations": iterations, "steps_per_iteration": 40, "output_dir": str(output_dir), "save_every": 1,
        "env": {"name": "gym:InvertedPendulum-v5", "num_envs": 2},
        "network": {"actor_hidden": [32, 32], "critic_hidden": [32, 32]},
        "algorithm": {"batch_size": 32, "learning_starts": 50, "utd_ratio": 0.25},
        "buffer": {"capacity": 100},
        "eval": {"every": 2, "episodes": 2, "num_envs": 2, "video_episodes": 0},
        "cluster": {"log_to_driver": False}, **extra,
    }
    return to_dataclass(SACConfig, raw)


def rows_of(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.parametrize("collect_ahead", [False, pytest.param(True, marks=pytest.mark.slow)],  # budget
                         ids=["sequential", "collect_ahead"])
def test_runs_and_resumes_exactly(ray_cluster, tmp_path, collect_ahead):
    video = {"video_episodes": 1, "video_max_steps": 8, "video_frame_skip": 1,
             "video_env_kwargs": {"width": 64, "height": 64}}
    straight = run(make_cfg(tmp_path / "straight", 4, collect_ahead=collect_ahead,
                            eval={"every": 2, "episodes": 2, "num_envs": 2, **video}))
    # keep_checkpoints=2 leaves iterations 3 and 4: the resumed run replays the collector's open
    # episodes and the wrapped-around buffer of iteration 3, and trains the last iteration.
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 3)
    resumed = run(make_cfg(tmp_path / "resumed", 4, collect_ahead=collect_ahead,
                           eval={"every": 2, "episodes": 2, "num_envs": 2, **video}))
    for key in ("weights_sha256", "actor_weights_sha256", "buffer_sha256", "env_steps"):
        assert resumed[key] == straight[key], key
    assert straight["env_steps"] == 4 * 2 * 40
    assert straight["devices"] == {"learner": "cpu"}  # read off the learner's parameters

    rows = rows_of(tmp_path / "straight" / "metrics.jsonl")
    assert [r["step"] for r in rows] == [0, 1, 2, 3, 4]
    assert rows[1]["rollout/random_action_fraction"] == 25 / 40  # warm-up ends inside iteration 1
    for key in ("rollout/episode_return_mean", "train/critic_loss", "train/actor_loss", "train/alpha",
                "train/entropy", "train/q_mean", "train/logprob_mismatch", "train/sample_age_mean",
                "rollout/max_staleness", "train/buffer_size", "env/steps", "time/env_steps_per_s"):
        assert key in rows[2], key
    if collect_ahead:  # iteration i's batch was collected with version i - 1 while the learner trained
        assert [r["rollout/max_staleness"] for r in rows[1:]] == [0.0, 1.0, 1.0, 1.0]
        assert rows[2]["train/logprob_mismatch"] > 1e-4  # the learner's actor has moved since
    else:
        assert rows[2]["train/logprob_mismatch"] < 1e-4  # collector and learner hold the same actor
        assert rows[2]["rollout/max_staleness"] == 0.0
    assert rows[4]["train/critic_loss"] > 0  # the resumed iteration trains
    assert rows[4]["train/buffer_size"] == 100 and rows[4]["train/updates"] == (320 - 50) // 4
    assert "eval/return_mean" in rows[0] and "eval/return_mean" in rows[2] and "eval/return_mean" not in rows[1]
    resumed_rows = rows_of(tmp_path / "resumed" / "metrics.jsonl")
    assert [r["step"] for r in resumed_rows] == [0, 1, 2, 3, 4]
    for a, b in zip(rows[1:], resumed_rows[1:]):
        for key in ("rollout/episode_return_mean", "rollout/reward_mean", "train/critic_loss", "train/alpha",
                    "eval/return_mean"):
            assert (a.get(key) == b.get(key)) or (a.get(key) != a.get(key)), (a["step"], key)  # equal or both NaN

    out = tmp_path / "straight"
    assert (out / "curves.png").stat().st_size > 0
    assert list((out / "tensorboard").iterdir())
    assert straight["video"] and (out / "eval.mp4").stat().st_size > 0
    checkpoints = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert checkpoints == ["iter_000003", "iter_000004"]  # keep_checkpoints=2, no temporary folders
    if not collect_ahead:
        check_pinned("sac", out, ["rollout/reward_mean", "train/critic_loss", "train/actor_loss", "train/alpha",
                                  "eval/return_mean"])
    files = sorted(p.relative_to(out / "checkpoints" / "iter_000004").as_posix()
                   for p in (out / "checkpoints" / "iter_000004").rglob("*") if p.is_file())
    expected = ["collector/collector.pt", "driver_rng.pt", "learner/learner.pt", "learner/replay_buffer.npz",
                "manifest.json", "runner_state.json"]
    if collect_ahead:  # the next iteration's batch, already collected: resume must not collect it again
        expected.insert(5, "pending_batch.pt")
    assert files == expected


def test_bad_config_fails_before_workers_start(tmp_path):
    with pytest.raises(ConfigError, match="unknown env family 'gymm'.*registered: .*gym"):
        make_cfg(tmp_path, 1, env={"name": "gymm:InvertedPendulum-v5"})
    with pytest.raises(ConfigError, match="learning_starts=10 must be >= algorithm.batch_size=32"):
        make_cfg(tmp_path, 1, algorithm={"batch_size": 32, "learning_starts": 10})
    with pytest.raises(ConfigError, match="placement.actor: the sac runner has no such component; its components "
                                          "are collector, learner"):
        make_cfg(tmp_path, 1, placement={"collector": "0", "actor": "0"})
    with pytest.raises(ConfigError, match="runs one learner rank"):
        make_cfg(tmp_path, 1, placement={"collector": "0", "learner": "0-1"})
    with pytest.raises(ConfigError, match=r"learner.device.*'gpu'.*auto.*cpu"):
        make_cfg(tmp_path, 1, learner={"device": "gpu"})
    with pytest.raises(ConfigError, match="unknown config key 'algorithm.utd'"):
        make_cfg(tmp_path, 1, algorithm={"utd": 2})
    # The task and its spaces are checked in the driver, before Ray starts any worker.
    with pytest.raises(ConfigError, match="Pendulum-v9"):
        run(make_cfg(tmp_path, 1, env={"name": "gym:Pendulum-v9"}))
    with pytest.raises(ConfigError, match="discrete actions"):
        run(make_cfg(tmp_path, 1, env={"name": "gym:CartPole-v1"}))
