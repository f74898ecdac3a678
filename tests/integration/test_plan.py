"""`infinirl plan` and `placement=auto` end to end on a tiny embodied config and a tiny robot run:
a real probe run measured from its spans, the profile cached, a second plan instant, and a run that
picks its own placement and records it; a runner with nothing to place says why."""

import json
import os
import subprocess
import sys

import pytest

# Tiny work, one CPU slot (one probe: the collocated one) so the test stays short.
TINY = ["env.num_envs=2", "rollout_steps=5", "algorithm.mini_batches=1", "algorithm.epochs=1", "cluster.num_cpus=1",
        "cluster.log_to_driver=false"]


@pytest.fixture
def profile_cache(tmp_path, monkeypatch):
    folder = tmp_path / "profiles"
    monkeypatch.setenv("INFINIRL_PROFILE_CACHE", str(folder))
    return folder


@pytest.mark.slow  # profiles and runs a config several times; the planner's parts have unit tests
def test_plan_profiles_once_then_reads_the_cache_and_auto_runs_the_best(tmp_path, profile_cache, monkeypatch,
                                                                        capsys):
    from infinirl.cli import main
    from infinirl.scheduler import profile as profiling

    assert main(["plan", "ppo_metaworld_reach", *TINY, "--profile-iterations", "2"]) == 0
    out = capsys.readouterr().out
    assert "candidate placements of embodied" in out
    assert "env=0 rollout=0 actor=0" in out  # the only placement one slot allows
    cached = list(profile_cache.glob("embodied-*.json"))
    assert len(cached) == 1
    profile = json.loads(cached[0].read_text())
    assert profile["costs"]["collect/env"]["per_unit_s"] > 0
    assert profile["costs"]["update/actor"]["per_unit_s"] > 0
    assert profile["costs"]["update/actor"]["memory_fixed_bytes"] > 0  # the actor process's peak RSS
    assert profile["key"]["cluster"] == {"nodes": [{"cpus": 1, "accelerators": []}]}  # the cluster planned for
    # the embodied runner keeps its components resident: no offload + reload is timed
    assert all(probe["switch_s"] == {} for probe in profile["probes"])

    def refuse(*args, **kwargs):
        raise AssertionError("the profile is cached: nothing may run again")

    monkeypatch.setattr(profiling, "run_probe", refuse)
    assert main(["plan", "ppo_metaworld_reach", *TINY]) == 0  # same work: the cache answers

    out_dir = tmp_path / "auto"
    assert main(["train", "ppo_metaworld_reach", *TINY, "placement=auto", "iterations=1", "eval.episodes=1",
                 "eval.num_envs=1", "eval.video_episodes=0", "loggers=[]", f"output_dir={out_dir}"]) == 0
    out = capsys.readouterr().out
    assert "placement=auto:" in out
    config = json.loads((out_dir / "config.json").read_text())
    assert config["placement"] == {"env": "0", "rollout": "0", "actor": "0"}
    assert config["rollout"]["pipeline_stages"] == 1


def test_plan_says_why_a_runner_has_nothing_to_place(capsys):
    from infinirl.cli import main

    assert main(["plan", "sft_vla_metaworld"]) == 2
    err = capsys.readouterr().err
    assert "nothing to plan: sft trains in one process" in err and "device=auto" in err


# The robot's episodes short (5 steps at 20 Hz) and one CPU slot (one probe: the collocated one).
ROBOT_TINY = ["task.max_episode_steps=5", "cluster.num_cpus=1", "cluster.log_to_driver=false"]


@pytest.mark.slow  # Ray starts twice and the robot runs in real time; the model's parts have unit tests
def test_plan_of_a_robot_run_profiles_turns_and_auto_places_the_learner(tmp_path, profile_cache, capsys):
    from infinirl.cli import main

    assert main(["plan", "realworld_sac_sawyer_reach", *ROBOT_TINY, "--profile-iterations", "2"]) == 0
    out = capsys.readouterr().out
    assert "candidate placements of realworld_sac" in out and "fixed (not searched): robot=0" in out
    assert "robot=0 learner=0" in out
    profile = json.loads(next(profile_cache.glob("realworld_sac-*.json")).read_text())
    assert profile["costs"]["iteration/robot"]["per_unit_s"] >= 0.05  # never faster than its 20 Hz clock
    assert profile["costs"]["iteration/learner"]["per_unit_s"] > 0

    out_dir = tmp_path / "auto"
    assert main(["train", "realworld_sac_sawyer_reach", *ROBOT_TINY, "placement=auto", "iterations=1",
                 "pipeline.iteration_s=1", "eval.episodes=1", "loggers=[]", f"output_dir={out_dir}"]) == 0
    assert "placement=auto:" in capsys.readouterr().out
    assert json.loads((out_dir / "config.json").read_text())["placement"] == {"robot": "0", "learner": "0"}


@pytest.mark.slow  # Ray starts and the robot runs in real time; the model's parts have unit tests
def test_plan_of_hg_dagger_profiles_one_episode_per_iteration(profile_cache, capsys):
    from infinirl.cli import main

    assert main(["plan", "hg_dagger_sawyer_reach", *ROBOT_TINY, "bc.updates_per_iteration=20",
                 "--profile-iterations", "2"]) == 0
    out = capsys.readouterr().out
    assert "candidate placements of hg_dagger" in out and "robot=0 learner=0" in out
    profile = json.loads(next(profile_cache.glob("hg_dagger-*.json")).read_text())
    assert profile["costs"]["collect/robot"]["per_unit_s"] >= 0.05  # never faster than its 20 Hz clock
    assert profile["costs"]["update/learner"]["per_unit_s"] > 0


def test_plan_of_a_robot_run_from_its_cached_profile_lists_the_learners_places(profile_cache, monkeypatch, capsys):
    """The CLI end to end on a profile already measured (fitted from known turns): no run, the
    robot stays where the config puts it and every CPU slot is a place for the learner."""
    from infinirl.cli import build_config
    from infinirl.runtime import ClusterInventory
    from infinirl.scheduler import profile as profiling
    from infinirl.scheduler.workloads import RUNNER_MODELS

    overrides = ["placement.robot=1", "cluster.num_cpus=3"]
    cfg = build_config("realworld_sac_sawyer_reach", overrides)[1]
    model = RUNNER_MODELS.get("realworld_sac")
    units = model.units(cfg)
    inventory = ClusterInventory.cpu_only(1, 3).to_dict()
    results = [profiling.ProbeResult(probe=probe, iterations=[{"iteration/robot": 0.055 * units["robot"],
                                                               "iteration/learner": 0.01 * units["learner"]}] * 2,
                                     step_s=[3.2] * 2, memory_bytes={"robot": 2.0**29, "learner": 2.0**29},
                                     switch_s={}, inventory=inventory) for probe in model.probes]
    key = profiling.profile_key(cfg, model, ClusterInventory.cpu_only(1, 3))  # the cluster cluster.num_cpus=3 starts
    profile_cache.mkdir()
    (profile_cache / profiling.cache_path(key, str(profile_cache)).rsplit("/", 1)[1]).write_text(
        json.dumps(profiling.fit(cfg, model, results, key).to_dict()))

    # In a process of its own: `plan` searches on the cluster it starts (3 CPUs), which in this
    # process would be the Ray instance an earlier test left running, of another size.
    done = subprocess.run([sys.executable, "-m", "infinirl.cli", "plan", "realworld_sac_sawyer_reach", *overrides],
                          capture_output=True, text=True, timeout=300, env={**os.environ})
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    assert "measuring " not in out  # the profile is cached: no probe ran
    assert "3 candidate placements of realworld_sac" in out and "step_s = one turn" in out
    cells = [line.split("  [")[0].split() for line in out.splitlines()]  # the row before its seconds per phase
    rows = [row for row in cells if row[-1:] and row[-1].startswith("learner=")]
    assert sorted(row[-1] for row in rows) == ["learner=0", "learner=1", "learner=2"]
    assert {row[-2] for row in rows} == {"robot=1"}
    assert {row[1] for row in rows} == {f"{0.055 * units['robot']:.3f}"}  # the robot's episode sets the pace
