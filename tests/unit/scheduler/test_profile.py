"""Profiling without Ray: spans cut into iterations, costs fitted from probes, the cache."""

import json

import pytest

from infinirl.cli import build_config
from infinirl.config import ConfigError
from infinirl.runtime import ClusterInventory
from infinirl.scheduler import profile as profiling
from infinirl.scheduler.cost import predict
from infinirl.scheduler.profile import ProbeResult, config_hash, fit, load_or_profile, step_windows, workload_of
from infinirl.scheduler.workloads import RUNNER_MODELS, probe_candidates


@pytest.fixture(scope="module")
def embodied_cfg():
    return build_config("ppo_metaworld_reach", ["env.num_envs=4", "rollout_steps=10", "algorithm.mini_batches=2"])[1]


def test_spans_are_cut_at_each_iteration_and_paired_with_metrics():
    model = RUNNER_MODELS.get("embodied")
    spans = []
    for i in range(3):  # iteration i starts at 10 i: collect 4 s on rank 0, update 1 s on ranks 0 and 1
        t = 10.0 * i
        spans += [("rollout", 0, "collect", t, t + 4.0, True), ("actor", 0, "update", t + 5, t + 6, True),
                  ("actor", 1, "update", t + 5, t + 6.5, True), ("rollout", 0, "evaluate", t + 7, t + 8, True)]
    rows = [{"step": i + 1, "time/iteration_s": 9.0 + i, "rollout/inference_s": 1.0} for i in range(3)]
    windows = step_windows(spans, rows, model, iterations=3)
    assert len(windows) == 3
    assert windows[1].per_rank("rollout", "collect") == pytest.approx(4.0)
    assert windows[1].per_rank("actor", "update") == pytest.approx(1.25)  # ranks work side by side: their mean
    assert windows[2].metrics["time/iteration_s"] == 11.0
    assert windows[0].last_end[("actor", "update")] == pytest.approx(6.5)


def _result(model, cfg, probe_name, per_iteration, step_s, memory=0.0):
    probe = next(p for p in model.probes if p.name == probe_name)
    return ProbeResult(probe=probe, iterations=[per_iteration] * 3, step_s=[step_s] * 3,
                       memory_bytes={"rollout": memory, "actor": memory, "env": memory},
                       switch_s={"actor": 0.01}, inventory=ClusterInventory.cpu_only(1, 2).to_dict())


def test_fit_recovers_the_costs_that_made_the_measurements(embodied_cfg):
    """Measurements made by known costs (env 2 ms, rollout 1 ms, actor 0.5 ms per decision; a
    second actor rank costs 0.3 s; a hop 1 ms; the driver 0.4 s) come back out of the fit."""
    model, cfg = RUNNER_MODELS.get("embodied"), embodied_cfg
    units = 40.0
    env, rollout, actor, hop, overhead = 0.002 * units, 0.001 * units, 0.0005 * units, 0.001, 0.4
    trips = cfg.rollout_steps + 1
    results = [
        _result(model, cfg, "collocated", {"collect/env": env, "collect/rollout": rollout, "update/actor": actor},
                env + rollout + actor + overhead, memory=1e9),
        _result(model, cfg, "two_ranks",
                {"collect/env": env / 2, "collect/rollout": rollout / 2, "update/actor": actor / 2 + 0.3},
                (env + rollout) / 2 + actor / 2 + 0.3 + overhead),
        _result(model, cfg, "streamed", {"collect/env": env, "collect/rollout": rollout, "update/actor": actor,
                                         "hop": hop, "bytes/env": 300.0 * units, "bytes/rollout": 8.0 * units},
                env + rollout + hop * trips + actor + overhead),
    ]
    profile = fit(cfg, model, results)
    assert profile.costs["collect/env"].per_unit_s == pytest.approx(0.002)
    assert profile.costs["update/actor"].per_unit_s == pytest.approx(0.0005)
    assert profile.costs["update/actor"].comm_s == pytest.approx(0.3)
    assert profile.costs["collect/rollout"].comm_s == pytest.approx(0.0)
    assert profile.costs["update/actor"].memory_fixed_bytes == pytest.approx(1e9)
    assert profile.costs["update/actor"].switch_s == pytest.approx(0.01)
    assert profile.hop_s == pytest.approx(hop)
    assert profile.costs["collect/env"].bytes_out_per_unit == pytest.approx(300.0)  # an observation's bytes
    assert profile.costs["collect/rollout"].bytes_out_per_unit == pytest.approx(8.0)
    assert profile.costs["update/actor"].bytes_out_per_unit == 0.0
    # the embodied runner keeps its components resident: the measured offload is no part of a step
    assert profile.overhead_s == pytest.approx(overhead)
    workload = workload_of(cfg, profile)
    components = tuple(cfg.components())
    for result in results:  # every probe is predicted as it was measured
        assert predict(workload, result.probe.candidate(components)).step_s == pytest.approx(result.step_s[0])


def test_config_hash_ignores_placement_and_length_not_the_work():
    base = build_config("ppo_metaworld_reach", [])[1]
    same = build_config("ppo_metaworld_reach", ["placement.rollout=1", "iterations=3", "rollout.pipeline_stages=2",
                                                "output_dir=/tmp/elsewhere", "eval.every=1"])[1]
    other = build_config("ppo_metaworld_reach", ["env.num_envs=32"])[1]
    assert config_hash(base) == config_hash(same)
    assert config_hash(base) != config_hash(other)


def test_a_cached_profile_is_read_without_running(tmp_path, monkeypatch, embodied_cfg):
    model, cfg = RUNNER_MODELS.get("embodied"), embodied_cfg
    two = ClusterInventory.cpu_only(1, 2)
    results = [_result(model, cfg, "collocated", {"collect/env": 0.1, "collect/rollout": 0.05, "update/actor": 0.02},
                       0.2)]
    key = profiling.profile_key(cfg, model, two)
    path = profiling.cache_path(key, str(tmp_path))
    (tmp_path / path.rsplit("/", 1)[1]).write_text(json.dumps(fit(cfg, model, results, key).to_dict()))

    def refuse(*args, **kwargs):
        raise AssertionError("a cached profile must not be measured again")

    monkeypatch.setattr(profiling, "run_probe", refuse)
    loaded = load_or_profile(cfg, two, cache_dir=str(tmp_path))
    assert loaded.key == key
    assert loaded.costs["collect/env"].per_unit_s == pytest.approx(0.1 / 40)
    changed = build_config("ppo_metaworld_reach", ["env.num_envs=8", "rollout_steps=10",
                                                   "algorithm.mini_batches=2"])[1]
    with pytest.raises(AssertionError, match="measured again"):
        load_or_profile(changed, two, cache_dir=str(tmp_path))
    # the same work on a cluster of another shape is another profile: its probes differ
    for other in (ClusterInventory.cpu_only(1, 4), ClusterInventory.cpu_only(2, 2),
                  ClusterInventory.with_gpus(1, 2, cpus_per_node=2)):
        with pytest.raises(AssertionError, match="measured again"):
            load_or_profile(cfg, other, cache_dir=str(tmp_path))


def test_probes_that_ran_on_another_cluster_shape_are_refused_naming_the_cluster_keys(tmp_path, monkeypatch):
    """A profile planned for a 4-slot cluster whose probes ran on 2 slots (cluster.num_cpus says
    another cluster) would rank placements the run cannot take: refused, not cached."""
    cfg = build_config("sac_inverted_pendulum", ["steps_per_iteration=50"])[1]

    def probe_on_two_slots(cfg, model, probe, iterations):
        return ProbeResult(probe=probe, iterations=[{"collect/collector": 0.5, "update/learner": 0.4}], step_s=[1.0],
                           inventory=ClusterInventory.cpu_only(1, 2).to_dict())

    monkeypatch.setattr(profiling, "run_probe", probe_on_two_slots)
    with pytest.raises(ConfigError, match=r"cluster\.\*: the probes ran on a cluster of 1 node\(s\) of 2 CPU slots .*"
                                          r"not the 1 node\(s\) of 4 CPU slots"):
        load_or_profile(cfg, ClusterInventory.cpu_only(1, 4), cache_dir=str(tmp_path))
    assert not list(tmp_path.iterdir())


def test_probes_count_accelerators_where_the_cluster_has_them(tmp_path, monkeypatch):
    """One GPU beside 16 vCPUs: components are placed on the GPU, so only the collocated probe fits
    (a two-rank probe would ask for a second GPU); on 16 CPU slots every probe runs."""
    model = RUNNER_MODELS.get("embodied")
    one_gpu = ClusterInventory.with_gpus(1, 1, cpus_per_node=16)
    assert profiling.probe_slots(one_gpu) == 1
    assert [p.name for p in probe_candidates(model, profiling.probe_slots(one_gpu))] == ["collocated"]
    assert profiling.probe_slots(ClusterInventory.cpu_only(1, 16)) == 16
    cfg = build_config("sac_inverted_pendulum", ["steps_per_iteration=50"])[1]
    ran = []

    def fake_probe(cfg, model, probe, iterations):
        ran.append(probe.name)
        return ProbeResult(probe=probe, iterations=[{"collect/collector": 0.5, "update/learner": 0.4}], step_s=[1.0],
                           inventory=one_gpu.to_dict())

    monkeypatch.setattr(profiling, "run_probe", fake_probe)
    load_or_profile(cfg, one_gpu, cache_dir=str(tmp_path))
    assert ran == ["collocated"]


def test_memory_compared_is_the_accelerators_on_accelerators_and_the_hosts_on_cpu_slots(embodied_cfg):
    """On GPUs a rank's device memory is its accelerator peak and its resident set is checked per
    node; on CPU slots the resident set is both. A component no rank of which could be read is
    unknown, not 0."""
    model, cfg = RUNNER_MODELS.get("embodied"), embodied_cfg
    components = tuple(cfg.components())
    probe = next(p for p in model.probes if p.name == "collocated")
    result = ProbeResult(probe=probe, iterations=[], step_s=[], memory_bytes={"actor": 3e9, "rollout": 2e9},
                         accelerator_bytes={"actor": 5e9})
    assert profiling.fit_memory("actor", [result], components, on_accelerators=True) == (5e9, 3e9, True)
    assert profiling.fit_memory("actor", [result], components, on_accelerators=False) == (3e9, 3e9, True)
    assert profiling.fit_memory("rollout", [result], components, on_accelerators=True) == (0.0, 2e9, False)
    assert profiling.fit_memory("env", [result], components, on_accelerators=False) == (0.0, 0.0, False)
    on_gpu = ClusterInventory.with_gpus(1, 2).to_dict()
    results = [ProbeResult(probe=probe, iterations=[{"collect/env": 0.1, "collect/rollout": 0.05,
                                                     "update/actor": 0.02}] * 2, step_s=[0.2] * 2,
                           memory_bytes={"actor": 3e9, "rollout": 2e9, "env": 1e9},
                           accelerator_bytes={"actor": 5e9, "env": 0.0}, inventory=on_gpu)]
    costs = fit(cfg, model, results).costs
    assert (costs["update/actor"].memory_fixed_bytes, costs["update/actor"].host_memory_bytes) == (5e9, 3e9)
    assert costs["collect/env"].memory_known and costs["collect/env"].memory_fixed_bytes == 0.0
    assert not costs["collect/rollout"].memory_known  # its ranks' accelerator peak was not read


@pytest.mark.parametrize("collect_ahead", [False, True])
def test_fit_recovers_sac_costs_with_and_without_collecting_ahead(collect_ahead):
    """Collector 1 ms per env step, learner 2 ms per update, the driver 0.2 s: the fit gets them back,
    and both probes are predicted as measured (apart and collecting ahead: the longer side only)."""
    cfg = build_config("sac_inverted_pendulum", [f"collect_ahead={collect_ahead}", "steps_per_iteration=50"])[1]
    model = RUNNER_MODELS.get("sac")
    units = model.units(cfg)
    collect, learn, overhead = 1e-3 * units["collector"], 2e-3 * units["learner"], 0.2
    phase_c, phase_l = ("iteration", "iteration") if collect_ahead else ("collect", "update")
    measured = {f"{phase_c}/collector": collect, f"{phase_l}/learner": learn}
    apart = max(collect, learn) if collect_ahead else collect + learn
    results = [ProbeResult(probe=next(p for p in model.probes if p.name == name), iterations=[measured] * 3,
                           step_s=[step] * 3, memory_bytes={}, switch_s={}, inventory={})
               for name, step in (("collocated", collect + learn + overhead), ("split", apart + overhead))]
    profile = fit(cfg, model, results)
    assert profile.costs[f"{phase_c}/collector"].per_unit_s == pytest.approx(1e-3)
    assert profile.costs[f"{phase_l}/learner"].per_unit_s == pytest.approx(2e-3)
    assert profile.overhead_s == pytest.approx(overhead)
    workload = workload_of(cfg, profile)
    for result in results:
        assert predict(workload, result.probe.candidate(tuple(cfg.components()))).step_s == pytest.approx(
            result.step_s[0])


def test_rounds_interleave_the_probes_and_merge_each_probes_runs(tmp_path, monkeypatch):
    """Two rounds run the probes A B A B, not A A B B, and each probe's profile takes both runs."""
    cfg = build_config("sac_inverted_pendulum", ["steps_per_iteration=50"])[1]
    order = []

    def fake_probe(cfg, model, probe, iterations):
        order.append(probe.name)
        step = 1.0 + len(order)  # a load that drifts up while profiling
        return ProbeResult(probe=probe, iterations=[{"collect/collector": 0.5, "update/learner": 0.4}],
                           step_s=[step], memory_bytes={"learner": float(len(order))}, switch_s={"learner": 0.1},
                           inventory={})

    monkeypatch.setattr(profiling, "run_probe", fake_probe)
    profile = load_or_profile(cfg, ClusterInventory.cpu_only(1, 2), cache_dir=str(tmp_path), rounds=2)
    assert order == ["collocated", "split", "collocated", "split"]
    by_name = {r.probe.name: r for r in profile.probes}
    assert by_name["collocated"].step_s == [2.0, 4.0] and by_name["split"].step_s == [3.0, 5.0]
    assert by_name["split"].memory_bytes["learner"] == 4.0  # the larger peak of its two runs
    with pytest.raises(ValueError, match="rounds=0 must be >= 1"):
        load_or_profile(cfg, ClusterInventory.cpu_only(1, 2), cache_dir=str(tmp_path), refresh=True, rounds=0)


def test_the_weight_sync_is_fitted_per_iteration_and_grows_with_the_trainers_ranks():
    """The reasoning runner's measured shape: generate 3.6 s and train 7.4 s on one rank, a little
    less on two; publishing the weights 0.57 s from one actor rank, 2.3 s from two (the shards are
    gathered first), loading 0.08 s / 0.11 s; the driver 0.2 s. The sync is one model's worth per
    iteration, so it is fitted as fixed seconds plus a cost per doubling of ranks: the probes come
    back as measured, two ranks each is predicted slower than one (as measured), and a batch 8
    times larger leaves the sync alone."""
    cfg = build_config("grpo_chain_sum", ["prompts_per_step=4"])[1]
    model = RUNNER_MODELS.get("reasoning")
    generate, train, publish, load, overhead = 3.6, 7.4, 0.57, 0.08, 0.2
    one = {"generate/rollout": generate, "generate/reward": 0.01, "train/actor": train,
           "sync/actor": publish, "sync/rollout": load}
    # two ranks each on two CPU slots: a rank has one thread where one rank had two, so compute barely shrinks
    two = {"generate/rollout": 3.36, "generate/reward": 0.01, "train/actor": 6.95, "sync/actor": 2.3,
           "sync/rollout": 0.11}
    results = [ProbeResult(probe=next(p for p in model.probes if p.name == name), iterations=[measured] * 3,
                           step_s=[sum(measured.values()) + overhead] * 3, memory_bytes={}, switch_s={},
                           inventory={})
               for name, measured in (("collocated", one), ("two_ranks", two))]
    profile = fit(cfg, model, results)
    sync = profile.costs["sync/actor"]
    assert (sync.per_unit_s, sync.fixed_s, sync.comm_s) == pytest.approx((0.0, publish, 2.3 - publish))
    assert profile.costs["sync/rollout"].fixed_s == pytest.approx(load)
    assert profile.overhead_s == pytest.approx(overhead)
    workload = workload_of(cfg, profile)
    components = tuple(cfg.components())
    predicted = {r.probe.name: predict(workload, r.probe.candidate(components)) for r in results}
    for result in results:
        assert predicted[result.probe.name].step_s == pytest.approx(result.step_s[0])
    assert predicted["two_ranks"].phases["sync"] == pytest.approx(2.41)
    assert predicted["two_ranks"].step_s > predicted["collocated"].step_s
    model.scale_batch(cfg, 8)
    bigger = workload_of(cfg, profile)
    assert bigger.cost("sync", "actor").seconds(bigger.units["actor"], 2) == pytest.approx(2.3)
    assert bigger.cost("train", "actor").seconds(bigger.units["actor"], 1) == pytest.approx(8 * train)
