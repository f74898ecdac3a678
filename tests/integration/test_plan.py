"""`infinirl plan` and `placement=auto` end to end on a tiny embodied config: a real probe run
measured from its spans, the profile cached, a second plan instant, and a run that picks its own
placement and records it."""

import json

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


def test_plan_refuses_a_runner_it_has_no_model_of(capsys):
    from infinirl.cli import main

    assert main(["plan", "realworld_sac_sawyer_reach"]) == 2
    err = capsys.readouterr().err
    assert "no model of the 'realworld_sac' runner" in err
