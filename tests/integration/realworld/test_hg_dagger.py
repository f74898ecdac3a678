"""HG-DAgger end to end through the command line as a user runs it (own process, own Ray): a
simulated human takes over the simulated Sawyer (MetaWorld reach) when the policy drifts; its steps
are stored with their flag and aggregated, and the policy is cloned on them each iteration. The
short run drives the arm in lockstep (one control period per command), so its metrics are a function
of its seeds and are pinned (tests/integration/pins.py); the slow runs drive it in real time."""

import importlib.util
import json
import subprocess
import sys

import pytest

from tests.integration.pins import check_pinned

pytestmark = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None, reason="needs metaworld")


def train(output_dir, *overrides, timeout=600):
    proc = subprocess.run([sys.executable, "-m", "infinirl.cli", "train", "hg_dagger_sawyer_reach",
                           f"output_dir={output_dir}", "loggers=[]", "cluster.log_to_driver=false", *overrides],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return [json.loads(line) for line in (output_dir / "metrics.jsonl").read_text().splitlines()]


def test_hg_dagger_cli_aggregates_the_simulated_humans_labels(tmp_path):
    rows = train(tmp_path / "run", "iterations=2", "dagger.episodes_per_iteration=2", "eval.episodes=1",
                 "eval.at_start=false", "task.max_episode_steps=25", "bc.updates_per_iteration=50",
                 "robot.options.control_hz=40.0", "+robot.options.lockstep=true", timeout=300)
    assert [r["step"] for r in rows] == [1, 2]
    for row in rows:
        for key in ("intervention/rate", "intervention/episode_rate", "intervention/takeovers_per_episode",
                    "rollout/success_rate", "eval/success_rate", "train/bc_loss", "dagger/dataset_rows"):
            assert key in row, key
        assert 0.0 <= row["intervention/rate"] <= 1.0
    # The dataset only grows, by the steps the human labelled (the initial demonstration's are in it first).
    assert rows[0]["dagger/dataset_rows"] >= rows[0]["dagger/added_rows"] > 0
    assert rows[1]["dagger/dataset_rows"] == rows[0]["dagger/dataset_rows"] + rows[1]["dagger/added_rows"]
    assert rows[1]["pipeline/version"] == 3  # the initial clone, then one version per iteration
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["dataset_rows"] == rows[1]["dagger/dataset_rows"]
    check_pinned("hg_dagger", tmp_path / "run", [
        "intervention/rate", "intervention/takeovers_per_episode", "dagger/dataset_rows", "dagger/novice_error",
        "train/bc_loss", "rollout/success_rate", "rollout/episode_length_mean", "eval/success_rate"])


@pytest.mark.slow
def test_hg_dagger_success_rises_and_interventions_fall(tmp_path):
    """The demo (infinirl/configs/hg_dagger_sawyer_reach.yaml): from a policy cloned on one
    demonstration, the simulated human's corrections teach it to reach: success rises, intervention
    rate falls."""
    rows = train(tmp_path / "demo", timeout=1200)
    evals = [r["eval/success_rate"] for r in rows if "eval/success_rate" in r]
    rates = [r["intervention/rate"] for r in rows if "intervention/rate" in r]
    assert max(evals[-3:]) >= evals[0] + 0.3
    assert sum(rates[-2:]) / 2 <= 0.5 * sum(rates[:2]) / 2


@pytest.mark.slow  # two runs of the command line
def test_hg_dagger_resumes_with_its_dataset(tmp_path):
    """Run again with more iterations: the learner (policy, optimiser, aggregate) comes back from the
    checkpoint, no demonstration is recorded again, and the dataset keeps growing from where it was."""
    small = ["dagger.episodes_per_iteration=1", "eval.episodes=1", "eval.at_start=false", "bc.updates_per_iteration=20",
             "task.max_episode_steps=20", "robot.options.control_hz=40.0"]
    first = train(tmp_path / "run", "iterations=1", *small, timeout=300)
    again = train(tmp_path / "run", "iterations=2", *small, timeout=300)
    assert [r["step"] for r in again] == [1, 2]
    assert again[1]["dagger/dataset_rows"] == first[0]["dagger/dataset_rows"] + again[1]["dagger/added_rows"]
    assert again[1]["pipeline/version"] == first[0]["pipeline/version"] + 1
    # New robot workers count from 0: the resumed run's steps go on from the checkpoint's by its one episode,
    # and so do the other robot counters.
    assert again[1]["env/steps"] == first[0]["env/steps"] + again[1]["rollout/episode_length_mean"]
    for key in ("robot/late_steps", "robot/safety_aborts", "robot/safety_clips", "robot/safety_events"):
        assert again[1][key] >= first[0][key], key


def config(**raw):
    from infinirl.config import to_dataclass
    from infinirl.runners.hg_dagger_config import HGDAggerConfig

    return to_dataclass(HGDAggerConfig, {"output_dir": "runs/test_hg_dagger", **raw})


@pytest.mark.parametrize("raw, message", [
    ({"dagger": {"demo_policy": "metaworld_expert", "demo_options": {"taks": "push-v3"}}},
     "dagger.demo_options.taks: not an option of demo policy 'metaworld_expert'; its options: task"),
    ({"dagger": {"demo_options": {"task": "reach-v3"}}},
     "dagger.demo_options.task: not an option of demo policy 'sawyer_goal'; its options: none"),
    ({"dagger": {"demo_options": {"seed": 3}}}, "dagger.demo_options.seed: the runner passes the robot env"),
    ({"interventions": {"device": "simulated_human", "as_demos": True}},
     "interventions.as_demos=true feeds RLPD's demonstrations store (realworld_sac)"),
    # what the robot env and the learner would refuse with a traceback once started
    ({"task": {"observations": []}}, "task.observations is empty; name at least one source"),
    ({"task": {"reward_options": {"classifier": {"path": "clf.pt"}}}},
     "task.reward_options: RobotEnvSpec.reward_options: ['classifier'] are not among the rewards"),
    ({"task": {"camera_names": {"wrist": "front"}}}, "task.camera_names: RobotEnvSpec.camera_names renames"),
    ({"task": {"frame_size": [64]}}, "task.frame_size=[64]: give [height, width]"),
    ({"placement": {"learner": "0,1"}}, "placement.learner='0,1': the learner is one rank"),
])
def test_config_errors_name_the_key_before_any_worker_starts(raw, message):
    from infinirl.config import ConfigError

    with pytest.raises(ConfigError) as error:
        config(**raw).validate()
    assert str(error.value).startswith(message) and "\n" not in str(error.value)
    config(dagger={"demo_policy": "metaworld_expert", "demo_options": {"task": "push-v3"}}).validate()


def test_validate_runs_the_hg_dagger_preflight(capsys):
    """`infinirl validate` builds the robot env's spec and the policy network as train does, and
    refuses what the config's own checks refuse with the same line."""
    from infinirl.cli import main
    from infinirl.runners import load_runners

    env, net = load_runners().get("hg_dagger").preflight(config())
    assert env.observations == ("proprio", "sim_state") and net.actor == "gaussian"
    assert main(["validate", "hg_dagger_sawyer_reach", "task.observations=[]"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("infinirl: config error: task.observations is empty") and err.count("\n") == 1


def test_the_robots_act_with_the_configured_network():
    from infinirl.realworld.robot_worker import unit_box
    from infinirl.runners.realworld_sac import net_spec_of

    net = net_spec_of(config(network={"actor_hidden": [16], "layer_norm": True}))
    assert any(type(m).__name__ == "LayerNorm" for m in net.build_actor(5, unit_box(2)).modules())


class Done:
    def __init__(self, value):
        self.value = value

    def wait(self, timeout=None):
        return self.value


class FakeRobot:
    """One robot rank of a group: it has counted ``steps`` training steps since it was built, one in
    five of them late and clipped once by the safety layer."""

    def __init__(self, steps=0):
        self.steps, self.filmed = steps, []

    def collect(self, episodes, deterministic):
        self.steps += 10 * episodes
        return Done([[]])

    def stats(self):
        return Done([{"counts": {"steps": self.steps, "late_steps": self.steps // 5}, "episodes": [],
                      "safety_clips": {"velocity": self.steps // 5}, "safety_events": {}}])

    def call(self, method, episodes, path, ranks):
        assert method == "record_video" and ranks == [0]
        self.filmed.append((episodes, path))
        return Done([{"path": path, "frames": 3, "success_rate": 0.0}])


class FakeLearner:
    def action_error(self, episodes):
        return Done([float("nan")])

    def aggregate(self, episodes):
        return Done([{"added": 0, "size": 5}])

    def train(self, updates):
        return Done([{"loss": 0.1, "updates": updates, "version": 0}])

    def published_version(self):
        return Done([0])  # nothing published: no weight sync

    def dataset_size(self):
        return Done([5])

    def save_checkpoint(self, path):
        return Done([None])

    load_checkpoint = save_checkpoint


def test_robot_counters_continue_across_a_resume_and_the_end_films_the_eval_video(tmp_path):
    """The robots count their steps (late ones, safety clips) from when they were started, so a resumed
    run adds its checkpoint's counts; after the last iteration robot rank 0 films ``eval.video_episodes``."""
    from infinirl.runners.hg_dagger import HGDAggerFlow

    cfg = config(dagger={"episodes_per_iteration": 2})
    first = HGDAggerFlow(cfg, FakeRobot(), FakeLearner())
    row = first.step(0)
    assert (row["env/steps"], row["robot/late_steps"], row["robot/safety_clips"]) == (20, 4, 4)
    state = first.save(str(tmp_path))
    resumed = HGDAggerFlow(cfg, FakeRobot(), FakeLearner())  # new robot workers count from 0
    resumed.load(str(tmp_path), state)
    row = resumed.step(1)
    assert (row["env/steps"], row["robot/late_steps"], row["robot/safety_clips"]) == (40, 8, 8)
    assert resumed.save(str(tmp_path)) == {"counts": {"env/steps": 40, "robot/late_steps": 8, "robot/safety_aborts": 0,
                                                      "robot/safety_clips": 8, "robot/safety_events": 0}}
    summary = resumed.finish(str(tmp_path))
    assert summary["video"] == str(tmp_path / "eval.mp4") and resumed.robots.filmed == [(1, summary["video"])]
    quiet = HGDAggerFlow(config(eval={"video_episodes": 0}), FakeRobot(), FakeLearner())
    assert quiet.finish(str(tmp_path))["video"] is None and quiet.robots.filmed == []
