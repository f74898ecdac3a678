"""The scheduler's models of the robot runners (realworld_sac, hg_dagger): the robots stay where the config puts
them, the robots' clock sets collection's pace, and the learner is placed; runners with nothing to
plan say why."""

import types

import pytest

from infinirl.cli import build_config
from infinirl.config import ConfigError
from infinirl.runtime import ClusterInventory, place
from infinirl.runtime.inventory import GiB
from infinirl.scheduler.auto import format_plan, runner_model
from infinirl.scheduler.cost import Allocation, Candidate, Phase, WorkCost, predict
from infinirl.scheduler.profile import ProbeResult, Profile, fit, workload_of
from infinirl.scheduler.search import search
from infinirl.scheduler.simulate import simulated_plan
from infinirl.scheduler.workloads import RUNNER_MODELS, StepWindow

MODEL = RUNNER_MODELS.get("realworld_sac")


def _cfg(*overrides):
    return build_config("realworld_sac_sawyer_reach", list(overrides))[1]


def _phase_keys(cfg):
    return ("iteration", "iteration") if cfg.pipeline.mode == "async" else ("collect", "update")


def _profile(cfg, robot_step_s=0.05, update_s=0.01, overhead_s=0.1):
    robot, learner = _phase_keys(cfg)
    costs = {f"{robot}/robot": WorkCost(per_unit_s=robot_step_s, memory_fixed_bytes=0.5 * GiB),
             f"{learner}/learner": WorkCost(per_unit_s=update_s, memory_fixed_bytes=0.5 * GiB)}
    return Profile(runner="realworld_sac", key={}, costs=costs, overhead_s=overhead_s, hop_s=0.0,
                   inventory=ClusterInventory.cpu_only(1, 2).to_dict(), probes=[])


def test_sync_mode_collects_then_updates_and_async_mode_does_both_at_once():
    sync, async_ = _cfg("pipeline.mode=sync"), _cfg("pipeline.mode=async")
    assert MODEL.phases(sync) == (Phase(name="collect", components=("robot",)),
                                  Phase(name="update", components=("learner",)))
    assert MODEL.phases(async_) == (Phase(name="iteration", components=("robot", "learner"), concurrent=True),)
    # one robot's episode (robots run side by side), the learner's updates on every robot's steps
    assert MODEL.units(sync) == {"robot": 50.0, "learner": 50.0}
    two = _cfg("placement.robot=0-1", "algorithm.utd_ratio=2")
    assert MODEL.units(two) == {"robot": 50.0, "learner": 200.0}
    capped = _cfg("pipeline.max_updates_per_step=4")  # async: the cap is the learner's work per step
    assert MODEL.units(capped)["learner"] == 200.0
    assert MODEL.driver_on_path(sync) and not MODEL.driver_on_path(async_)


def test_the_robots_clock_is_the_configs_control_rate():
    assert MODEL.paced(_cfg()) == {"robot": pytest.approx(1 / 20)}
    assert MODEL.paced(_cfg("robot.options.control_hz=10")) == {"robot": pytest.approx(0.1)}
    fleet = _cfg("placement.robot=0-1", "robot.fleet=[{kind: sim_sawyer, options: {task: reach-v3, control_hz: 20, "
                 "image_size: null}}, {kind: sim_sawyer, options: {task: reach-v3, control_hz: 5, "
                 "image_size: null}}]")
    assert MODEL.paced(fleet) == {"robot": pytest.approx(0.2)}  # the slowest robot sets a turn's pace
    assert MODEL.units(fleet)["learner"] == 100.0


def test_robots_are_fixed_where_the_config_puts_them():
    assert MODEL.fixed(_cfg()) == {"robot": "0"}
    assert MODEL.fixed(_cfg("placement.robot=robot:0")) == {"robot": "robot:0"}
    auto = _cfg("placement=auto")
    assert MODEL.fixed(auto) == {"robot": "0"}
    MODEL.apply(auto, Candidate(allocations={"robot": _alloc(0), "learner": _alloc(1)}))
    assert auto.placement == {"robot": "0", "learner": "1"}
    real = _cfg("placement.robot=robot:0")
    MODEL.apply(real, Candidate(allocations={"robot": _alloc(2), "learner": _alloc(0)}))
    assert real.placement == {"robot": "robot:0", "learner": "0"}  # the robot's allocation is never written


def _alloc(first, count=1):
    return Allocation(first=first, count=count, ranks=count)


def test_the_learner_is_one_rank_on_one_device():
    cfg = _cfg()
    assert MODEL.check(cfg, Candidate(allocations={"robot": _alloc(0), "learner": _alloc(1)})) is None
    assert "one rank" in MODEL.check(cfg, Candidate(allocations={"robot": _alloc(0), "learner": _alloc(0, 2)}))


def test_the_profile_runs_turns_of_the_same_work_without_touching_the_configs_store():
    cfg = _cfg("pipeline.max_updates_per_step=3", "replay.path=/data/robot_store", "demos.episodes=10")
    MODEL.shorten(cfg, 3)
    assert cfg.iterations == 3 and cfg.pipeline.mode == "sync" and cfg.pipeline.iteration_s < 0.01
    assert cfg.algorithm.utd_ratio == 3.0  # the asynchronous cap, run in turns
    assert cfg.algorithm.learning_starts == 1 and cfg.demos.episodes == 0
    assert cfg.replay.path is None  # the probe's own store, under its temporary output folder
    assert cfg.save_every == 0 and cfg.eval.every == 0 and not cfg.resume


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_a_turn_is_measured_per_config_episode_and_update(mode):
    """An episode that ended after 25 of 50 steps in 1.3 s, and 50 updates (2 robots x 25 steps)
    in 0.5 s: a full episode is 2.6 s, the config's 100 updates 1.0 s."""
    cfg = _cfg(f"pipeline.mode={mode}", "placement.robot=0-1")
    window = StepWindow(busy={("robot", "collect"): [1.3, 1.3], ("learner", "add_and_update"): [0.5]},
                        last_end={}, metrics={"rollout/episode_length_mean": 25.0, "rollout/episodes": 2.0})
    measured = MODEL.measure(window, MODEL.probes[0], cfg)
    robot, learner = _phase_keys(cfg)
    assert measured == {f"{robot}/robot": pytest.approx(2.6), f"{learner}/learner": pytest.approx(1.0)}
    empty = StepWindow(busy={}, last_end={}, metrics={})
    assert MODEL.measure(empty, MODEL.probes[0], cfg) == {}


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_fit_recovers_the_costs_and_predicts_the_pace(mode):
    """Robot steps of 55 ms (a 50 ms period and its reset), updates of 10 ms, a driver of 0.3 s per
    turn (on the path in sync mode only): the fit gets them back; a sync turn is the sum, an
    async one the robots' episode when the learner keeps up, and the learner's work when it does not."""
    cfg = _cfg(f"pipeline.mode={mode}")
    units = MODEL.units(cfg)
    robot, learner = _phase_keys(cfg)
    collect, update, overhead = 0.055 * units["robot"], 0.01 * units["learner"], 0.3
    measured = {f"{robot}/robot": collect, f"{learner}/learner": update}
    results = [ProbeResult(probe=p, iterations=[measured] * 3, step_s=[collect + update + overhead] * 3,
                           memory_bytes={}, switch_s={}, inventory={}) for p in MODEL.probes]
    profile = fit(cfg, MODEL, results)
    assert profile.costs[f"{robot}/robot"].per_unit_s == pytest.approx(0.055)
    assert profile.costs[f"{learner}/learner"].per_unit_s == pytest.approx(0.01)
    assert profile.overhead_s == pytest.approx(overhead if mode == "sync" else 0.0)  # async: off the path
    workload = workload_of(cfg, profile)
    assert workload.costs[f"{robot}/robot"].paced_per_unit_s == pytest.approx(0.05)
    for probe in MODEL.probes:
        step = predict(workload, probe.candidate(("robot", "learner"))).step_s
        assert step == pytest.approx(collect + update + overhead if mode == "sync" else collect)
    slow = workload_of(cfg, _profile(cfg, robot_step_s=0.05, update_s=0.2, overhead_s=0.3))
    expected = 0.05 * 50 + 0.2 * 50 + 0.3 if mode == "sync" else 0.2 * 50  # the learner falls behind
    assert predict(slow, MODEL.probes[0].candidate(("robot", "learner"))).step_s == pytest.approx(expected)


@pytest.mark.parametrize("robot", ["0", "1", "robot:0"])
def test_the_search_places_the_learner_only(robot):
    cfg = _cfg(f"placement.robot={robot}", "pipeline.mode=async")
    inventory = ClusterInventory.cpu_only(1, 4)
    entries = search(cfg, MODEL, workload_of(cfg, _profile(cfg)), inventory)
    assert sorted(e.placement["learner"] for e in entries) == ["0", "1", "2", "3"]
    assert {e.placement["robot"] for e in entries} == {robot}
    if not robot.startswith("robot:"):  # the cluster has no robots to place on
        for entry in entries:
            assert place(inventory, entry.placement, components=["robot", "learner"]).world_size("learner") == 1
    assert entries[0].prediction.step_s == pytest.approx(0.05 * 50)  # the robot's pace, wherever the learner is
    text = format_plan(cfg, None, entries)
    assert "step_s = one turn" in text and f"fixed (not searched): robot={robot}" in text


def test_a_simulated_gpu_cluster_keeps_the_robot_and_its_pace():
    cfg = _cfg("pipeline.mode=async")
    _, entries = simulated_plan(cfg, _profile(cfg, update_s=0.2), 8, speedup=4.0)
    assert len(entries) == 8 and {e.placement["robot"] for e in entries} == {"0"}
    # the learner is 4x faster on the simulated devices (0.05 s per update); the robot is not
    assert entries[0].prediction.step_s == pytest.approx(0.05 * 50)


def test_runners_and_configs_with_nothing_to_plan_say_why_and_what_to_write():
    with pytest.raises(ConfigError, match="nothing to plan: sft trains in one process.*device=auto"):
        runner_model(build_config("sft_vla_metaworld", [])[1])
    with pytest.raises(ConfigError, match="nothing to plan: runtime_demo demonstrates.*placement.sampler"):
        runner_model(build_config("runtime_demo", [])[1])
    with pytest.raises(ConfigError, match="pipeline.transport=edge.*placement.learner by hand"):
        runner_model(_cfg("pipeline.transport=edge", "edge.certs=/tmp/pki"))
    with pytest.raises(ConfigError, match="no model of the 'unknown' runner; it plans .*realworld_sac"):
        runner_model(types.SimpleNamespace(runner="unknown"))
    assert runner_model(_cfg()) is MODEL


def test_placement_auto_on_sft_is_refused_when_the_config_loads_not_ignored():
    with pytest.raises(ConfigError, match="placement=auto: sft trains in one process.*device=auto"):
        build_config("sft_vla_metaworld", ["placement=auto"])


def test_placement_auto_on_a_robot_run_loads_and_is_resolved_when_it_starts():
    cfg = _cfg("placement=auto")
    assert cfg.auto_placement  # the learner's one-rank rule is the model's check, applied by the search


def test_the_learner_alone_auto_beside_robots_the_config_places():
    cfg = _cfg("placement.robot=robot:0", "placement.learner=auto")
    assert cfg.auto_placement and MODEL.fixed(cfg) == {"robot": "robot:0"}
    entries = search(cfg, MODEL, workload_of(cfg, _profile(cfg)), ClusterInventory.cpu_only(1, 2))
    assert {e.placement["learner"] for e in entries} == {"0", "1"}  # one rank, on either slot
    assert all(e.placement["robot"] == "robot:0" for e in entries)
    two = _cfg("placement.robot=0-1", "placement.learner=auto")
    assert MODEL.units(two)["learner"] == 100.0  # the robots the config gives, not auto's one
    with pytest.raises(ConfigError, match="placement.learner='0-1': the learner is one rank"):
        _cfg("placement.robot=0", "placement.learner=0-1")


# ----- hg_dagger -----

DAGGER = RUNNER_MODELS.get("hg_dagger")


def _dagger(*overrides):
    return build_config("hg_dagger_sawyer_reach", list(overrides))[1]


def test_hg_dagger_collects_its_episodes_then_trains_its_updates():
    cfg = _dagger("dagger.episodes_per_iteration=6", "task.max_episode_steps=40", "bc.updates_per_iteration=300")
    assert DAGGER.phases(cfg) == (Phase(name="collect", components=("robot",)),
                                  Phase(name="update", components=("learner",)))
    assert DAGGER.units(cfg) == {"robot": 240.0, "learner": 300.0}
    assert DAGGER.paced(cfg) == {"robot": pytest.approx(1 / 20)}
    assert DAGGER.fixed(_dagger("placement.robot=robot:0")) == {"robot": "robot:0"}
    short = _dagger("dagger.initial_demos=3")
    DAGGER.shorten(short, 2)
    assert short.dagger.episodes_per_iteration == 1 and short.dagger.initial_demos == 1
    assert not short.eval.at_start and short.eval.every == 0 and short.iterations == 2
    none = _dagger("dagger.initial_demos=0")
    DAGGER.shorten(none, 2)
    assert none.dagger.initial_demos == 0  # a config that records none may have no demo policy for its robot


def test_hg_dagger_measures_one_episode_and_scales_it_to_the_configs():
    """One 20-step episode in 1.1 s, the learner's calls 0.2 + 0.1 + 2.0 s, a step of 3.6 s: six
    40-step episodes are 13.2 s, the learner 2.3 s, the driver 0.2 s."""
    cfg = _dagger("dagger.episodes_per_iteration=6", "task.max_episode_steps=40")
    window = StepWindow(busy={("robot", "collect"): [1.1], ("learner", "action_error"): [0.2],
                              ("learner", "aggregate"): [0.1], ("learner", "train"): [2.0]}, last_end={},
                        metrics={"rollout/episode_length_mean": 20.0, "rollout/episodes": 1.0,
                                 "time/iteration_s": 3.6})
    measured = DAGGER.measure(window, DAGGER.probes[0], cfg)
    assert measured == {"collect/robot": pytest.approx(13.2), "update/learner": pytest.approx(2.3),
                        "overhead": pytest.approx(0.2)}


def test_hg_dagger_fit_takes_the_drivers_measured_time_and_predicts_turns():
    cfg = _dagger("dagger.episodes_per_iteration=6", "task.max_episode_steps=40", "bc.updates_per_iteration=300")
    measured = {"collect/robot": 0.055 * 240, "update/learner": 0.004 * 300, "overhead": 0.2}
    # the probe ran one episode: its step time is far below the config's, the driver's time is not
    results = [ProbeResult(probe=p, iterations=[measured] * 3, step_s=[0.055 * 40 + 1.2 + 0.2] * 3, memory_bytes={},
                           switch_s={}, inventory={}) for p in DAGGER.probes]
    profile = fit(cfg, DAGGER, results)
    assert profile.costs["collect/robot"].per_unit_s == pytest.approx(0.055)
    assert profile.costs["update/learner"].per_unit_s == pytest.approx(0.004)
    assert profile.overhead_s == pytest.approx(0.2)
    entries = search(cfg, DAGGER, workload_of(cfg, profile), ClusterInventory.cpu_only(1, 2))
    assert [e.placement for e in entries] == [{"robot": "0", "learner": "0"}, {"robot": "0", "learner": "1"}]
    assert entries[0].prediction.step_s == pytest.approx(0.055 * 240 + 1.2 + 0.2)
