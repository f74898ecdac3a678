"""The search on this machine's kind of cluster and on simulated ones of 8 to 1,024 GPUs."""

import pytest

from infinirl.cli import build_config
from infinirl.runtime import ClusterInventory, place
from infinirl.runtime.inventory import GiB
from infinirl.scheduler.auto import format_plan
from infinirl.scheduler.cost import WorkCost, predict
from infinirl.scheduler.profile import Profile, workload_of
from infinirl.scheduler.search import MAX_LAYOUTS, candidate_layouts, pool_of, search
from infinirl.scheduler.simulate import scaled_config, simulated_plan
from infinirl.scheduler.workloads import RUNNER_MODELS


def _profile(runner, costs, overhead_s=0.1, hop_s=1e-4, inventory=None):
    return Profile(runner=runner, key={}, costs=costs, overhead_s=overhead_s, hop_s=hop_s,
                   inventory=(inventory or ClusterInventory.cpu_only(1, 2)).to_dict(), probes=[])


@pytest.fixture(scope="module")
def embodied():
    cfg = build_config("ppo_metaworld_reach", [])[1]
    gib = float(GiB)
    costs = {"collect/env": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=0.3 * gib),
             "collect/rollout": WorkCost(per_unit_s=4e-4, memory_fixed_bytes=0.4 * gib),
             "update/actor": WorkCost(per_unit_s=5e-4, comm_s=0.2, memory_fixed_bytes=0.7 * gib),
             "sync/actor": WorkCost(per_unit_s=0.0, fixed_s=0.01), "sync/rollout": WorkCost(per_unit_s=0.0)}
    return cfg, _profile("embodied", costs)


@pytest.fixture(scope="module")
def reasoning():
    cfg = build_config("grpo_chain_sum", [])[1]
    gib = float(GiB)
    costs = {"generate/rollout": WorkCost(per_unit_s=0.2, comm_s=0.5, memory_fixed_bytes=1.0 * gib),
             "generate/reward": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=0.5 * gib),
             "train/actor": WorkCost(per_unit_s=0.1, comm_s=1.0, memory_fixed_bytes=2.0 * gib),
             "sync/actor": WorkCost(per_unit_s=0.0, fixed_s=0.01), "sync/rollout": WorkCost(per_unit_s=0.0)}
    return cfg, _profile("reasoning", costs)


def _sac(collect_ahead: bool):
    cfg = build_config("sac_inverted_pendulum", [f"collect_ahead={collect_ahead}"])[1]
    gib = float(GiB)
    phase = ("iteration", "iteration") if collect_ahead else ("collect", "update")
    costs = {f"{phase[0]}/collector": WorkCost(per_unit_s=2e-3, memory_fixed_bytes=0.3 * gib),
             f"{phase[1]}/learner": WorkCost(per_unit_s=3e-3, memory_fixed_bytes=0.3 * gib)}
    return cfg, _profile("sac", costs)


@pytest.fixture(scope="module")
def sac():
    return _sac(collect_ahead=False)


@pytest.fixture(scope="module")
def sac_ahead():
    return _sac(collect_ahead=True)


def _valid(cfg, entry, inventory):
    """Every component placed, by a spec place() accepts, with the ranks the candidate counted."""
    plan = place(inventory, entry.placement, components=cfg.components())
    assert set(plan.components) == set(cfg.components())
    for name, allocation in entry.candidate.allocations.items():
        assert plan.world_size(name) == allocation.ranks
    assert entry.memory_bytes <= entry.memory_limit_bytes


@pytest.mark.parametrize("fixture", ["embodied", "reasoning", "sac", "sac_ahead"])
def test_every_candidate_on_two_cpu_slots_is_valid_and_the_first_is_the_fastest(fixture, request):
    cfg, profile = request.getfixturevalue(fixture)
    inventory = ClusterInventory.cpu_only(1, 2)
    model = RUNNER_MODELS.get(cfg.runner)
    entries = search(cfg, model, workload_of(cfg, profile), inventory)
    assert len(entries) >= 2
    for entry in entries:
        _valid(cfg, entry, inventory)
        assert model.check(cfg, entry.candidate) is None
    times = [e.prediction.step_s for e in entries]
    assert times == sorted(times)
    # brute force over every layout and depth: nothing valid beats the first entry
    workload = workload_of(cfg, profile)
    from infinirl.scheduler.cost import Candidate

    best = min(predict(workload, Candidate(allocations=layout, depth=d)).step_s
               for layout in candidate_layouts(tuple(cfg.components()), 2)
               for d in model.depths(cfg, {n: a.ranks for n, a in layout.items()})
               if model.check(cfg, Candidate(allocations=layout, depth=d)) is None)
    assert times[0] == pytest.approx(best)


def test_the_embodied_search_covers_every_execution_mode(embodied):
    cfg, profile = embodied
    three = ClusterInventory.cpu_only(1, 3)  # three components apart need three slots
    entries = search(cfg, RUNNER_MODELS.get("embodied"), workload_of(cfg, profile), three)
    modes = {place(three, e.placement).mode for e in entries}
    assert modes == {"collocated", "disaggregated", "hybrid"}
    assert {e.candidate.depth for e in entries} == {1, 2, 4}
    # a streamed env with 2 stages overlaps simulation and inference: predicted faster than 1 stage
    by_key = {(tuple(sorted(e.placement.items())), e.candidate.depth): e.prediction.step_s for e in entries}
    streamed = tuple(sorted({"env": "0", "rollout": "1", "actor": "0"}.items()))
    assert by_key[(streamed, 2)] < by_key[(streamed, 1)]


def test_memory_rules_out_collocating_what_does_not_fit(embodied):
    cfg, profile = embodied
    model = RUNNER_MODELS.get("embodied")
    workload = workload_of(cfg, profile)
    # GPUs of 1 GiB: env (0.3) + rollout (0.4) fit together, the actor (0.7) with the rollout does not
    inventory = ClusterInventory.with_gpus(1, 4, gpu_memory_bytes=GiB)
    entries = search(cfg, model, workload, inventory)
    assert entries
    for entry in entries:
        a = entry.candidate.allocations
        assert not a["actor"].overlaps(a["rollout"])
        assert entry.memory_bytes <= GiB
    roomy = search(cfg, model, workload, ClusterInventory.with_gpus(1, 4, gpu_memory_bytes=8 * GiB))
    assert any(e.candidate.allocations["actor"].overlaps(e.candidate.allocations["rollout"]) for e in roomy)


def test_cpu_slots_share_their_node_memory(embodied):
    cfg, profile = embodied
    tight = ClusterInventory.from_dict({"nodes": [{**ClusterInventory.cpu_only(1, 2).to_dict()["nodes"][0],
                                                   "memory_bytes": int(1.5 * GiB)}]})
    assert pool_of(tight).on_cpu
    entries = search(cfg, RUNNER_MODELS.get("embodied"), workload_of(cfg, profile), tight)
    # 1.4 GiB for one rank of each; two env/rollout ranks (2 x 0.7 GiB) and an actor do not fit
    assert entries and all(e.candidate.allocations["rollout"].ranks == 1 for e in entries)


@pytest.mark.parametrize("num_gpus", [8, 64, 1024])
@pytest.mark.parametrize("fixture", ["embodied", "reasoning"])
def test_simulated_clusters_plan_valid_placements_within_memory(fixture, num_gpus, request):
    cfg, profile = request.getfixturevalue(fixture)
    inventory, entries = simulated_plan(cfg, profile, num_gpus, speedup=20.0, gpu_memory_bytes=80 * GiB)
    assert entries
    scaled = scaled_config(cfg, num_gpus)
    model = RUNNER_MODELS.get(cfg.runner)
    for entry in entries[:3]:
        _valid(scaled, entry, inventory)
        assert model.check(scaled, entry.candidate) is None
    assert all(e.memory_bytes <= 80 * GiB for e in entries)
    best = entries[0].candidate.allocations
    assert max(a.first + a.count for a in best.values()) <= num_gpus
    if num_gpus == 1024:  # every block order over 128 nodes: a coarser grid, which the table says
        assert entries.grid == [1, 4, 16, 64, 256, 1024] and not entries.truncated
        assert "(a finer grid gives more than 4000 layouts)" in format_plan(scaled, None, entries)


def test_simulated_memory_limit_is_respected(reasoning):
    cfg, profile = reasoning
    # 2.5 GiB GPUs: the actor (2 GiB) cannot share a GPU with the rollout (1 GiB)
    _, entries = simulated_plan(cfg, profile, 64, gpu_memory_bytes=int(2.5 * GiB))
    assert entries
    for entry in entries:
        a = entry.candidate.allocations
        assert not a["actor"].overlaps(a["rollout"])
        assert entry.memory_bytes <= 2.5 * GiB


@pytest.mark.parametrize("fixture", ["sac", "sac_ahead"])
def test_sac_collecting_ahead_on_its_own_slot_overlaps_collection_and_learning(fixture, request):
    """collect_ahead: the collector on its own slot works while the learner trains (the longer one
    sets the pace); on one slot they take turns. Without it they always take turns."""
    cfg, profile = request.getfixturevalue(fixture)
    entries = search(cfg, RUNNER_MODELS.get("sac"), workload_of(cfg, profile), ClusterInventory.cpu_only(1, 2))
    steps = cfg.steps_per_iteration * cfg.env.num_envs
    collect, learn = 2e-3 * steps, 3e-3 * cfg.algorithm.utd_ratio * steps
    by_layout = {(e.placement["collector"] == e.placement["learner"]): e.prediction.step_s for e in entries}
    assert by_layout[True] == pytest.approx(collect + learn + 0.1)  # one slot: turns (+ the driver's 0.1 s)
    apart = max(collect, learn) if cfg.collect_ahead else collect + learn
    assert by_layout[False] == pytest.approx(apart + 0.1)
    assert entries[0].placement["collector"] != entries[0].placement["learner"] or not cfg.collect_ahead


def test_grouped_multi_task_candidates_give_every_group_one_task():
    """GRPO on two tasks needs each rank's and stage's envs in blocks of group_size x tasks: the
    search proposes only layouts the runner accepts."""
    from infinirl.runners.embodied import task_blocks_conflict

    cfg = build_config("grpo_metaworld_reach", ["env.name='metaworld:reach-v3,push-v3'", "env.num_envs=16",
                                                "algorithm.group_size=4"])[1]
    gib = float(GiB)
    costs = {"collect/env": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=0.3 * gib),
             "collect/rollout": WorkCost(per_unit_s=4e-4, memory_fixed_bytes=0.4 * gib),
             "update/actor": WorkCost(per_unit_s=5e-4, comm_s=0.2, memory_fixed_bytes=0.7 * gib),
             "sync/actor": WorkCost(per_unit_s=0.0, fixed_s=0.01), "sync/rollout": WorkCost(per_unit_s=0.0)}
    inventory = ClusterInventory.cpu_only(1, 4)
    profile = _profile("embodied", costs, inventory=inventory)
    entries = search(cfg, RUNNER_MODELS.get(cfg.runner), workload_of(cfg, profile), inventory)
    assert entries
    for entry in entries:
        ranks = entry.candidate.allocations["rollout"].ranks
        assert task_blocks_conflict(cfg, ranks, entry.candidate.depth) is None


def _best(cfg, profile, inventory):
    entries = search(cfg, RUNNER_MODELS.get(cfg.runner), workload_of(cfg, profile), inventory)
    assert entries, entries.why_empty()
    return entries


@pytest.mark.parametrize("size", [5, 8])
@pytest.mark.parametrize("fixture", ["embodied", "reasoning", "sac", "sac_ahead"])
def test_a_larger_pool_never_predicts_worse_than_four_of_its_devices(fixture, size, request):
    """Every layout of the first 4 devices is a layout of a larger pool, so its best is no slower."""
    cfg, profile = request.getfixturevalue(fixture)
    four = _best(cfg, profile, ClusterInventory.cpu_only(1, 4))[0].prediction.step_s
    assert _best(cfg, profile, ClusterInventory.cpu_only(1, size))[0].prediction.step_s <= four + 1e-9


def test_eight_slots_find_what_eight_allow(embodied):
    """Streamed env and rollout on four slots each, the actor beside the env and one rollout slot
    (a spanning component taking part of the blocks, the blocks in stream order): the search sees
    it and ranks nothing above what it predicts."""
    cfg, profile = embodied
    entries = _best(cfg, profile, ClusterInventory.cpu_only(1, 8))
    by_key = {(tuple(sorted(e.placement.items())), e.candidate.depth): e.prediction.step_s for e in entries}
    split = (tuple(sorted({"env": "0-3", "rollout": "4-7", "actor": "0-4"}.items())), 2)
    assert by_key[split] == pytest.approx(1.134, abs=1e-3)
    assert entries[0].prediction.step_s <= by_key[split]
    assert entries[0].prediction.step_s < _best(cfg, profile, ClusterInventory.cpu_only(1, 4))[0].prediction.step_s


@pytest.mark.parametrize("size", [5, 8, 16])
@pytest.mark.parametrize("fixture", ["sac", "sac_ahead"])
def test_sac_on_more_than_four_slots_has_candidates_collocated_among_them(fixture, size, request):
    cfg, profile = request.getfixturevalue(fixture)
    entries = _best(cfg, profile, ClusterInventory.cpu_only(1, size))
    assert {"collector": "0", "learner": "0"} in [e.placement for e in entries]
    assert all(a.ranks == 1 for e in entries for a in e.candidate.allocations.values())


def test_layouts_stay_bounded_and_say_when_their_sizes_are_coarser():
    """Up to MAX_LAYOUTS structured layouts: three components on one node of 8 or 16 devices keep
    every grid size; on 1,024 GPUs over nodes, or with four components, the grid is coarser and
    the result says which."""
    three, four = ("a", "b", "c"), ("a", "b", "c", "d")
    for components, size, every_order, fine in ((three, 8, False, True), (three, 16, False, True),
                                                (three, 64, True, False), (three, 1024, True, False),
                                                (four, 8, False, False)):
        layouts = candidate_layouts(components, size, every_order=every_order)
        listed = list(layouts)
        exhaustive = 10 ** len(components)  # the 10 ranges of 4 devices, for each component
        assert len(listed) == layouts.count <= exhaustive + MAX_LAYOUTS
        assert layouts.fine == fine and not layouts.truncated
        assert len({tuple((a.first, a.count) for a in layout.values()) for layout in listed}) == len(listed)
        assert any(all((layout[n].first, layout[n].count) == (0, size) for n in components) for layout in listed)
    # every layout of the first 4 devices is one of a larger pool's
    spans = lambda layouts: {tuple((a.first, a.count) for a in layout.values()) for layout in layouts}  # noqa: E731
    assert spans(candidate_layouts(three, 4)) <= spans(candidate_layouts(three, 8, every_order=False))
    # every order of the blocks where a node boundary can make it count
    ordered = [{n: (a.first, a.count) for n, a in layout.items()} for layout in candidate_layouts(three, 16)]
    assert {"a": (0, 8), "b": (8, 8), "c": (8, 8)} in ordered and {"b": (0, 8), "c": (0, 8), "a": (8, 8)} in ordered
    assert {"a": (0, 4), "b": (0, 2), "c": (4, 4)} in ordered  # a member taking part of its block


def test_host_memory_is_checked_per_node_on_gpus_and_a_rejection_says_what_ruled_out(embodied):
    """On GPUs a rank's host memory fills its node (16 GiB here: four 6 GiB ranks do not fit) while
    its device memory fills its GPU; what was left out is counted by reason."""
    cfg, _ = embodied
    gib = float(GiB)
    costs = {"collect/env": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=0.3 * gib, host_memory_bytes=6 * gib),
             "collect/rollout": WorkCost(per_unit_s=4e-4, memory_fixed_bytes=0.4 * gib, host_memory_bytes=0.1 * gib),
             "update/actor": WorkCost(per_unit_s=5e-4, memory_fixed_bytes=0.7 * gib, host_memory_bytes=0.1 * gib),
             "sync/actor": WorkCost(per_unit_s=0.0, fixed_s=0.01), "sync/rollout": WorkCost(per_unit_s=0.0)}
    inventory = ClusterInventory.from_dict({"nodes": [{**ClusterInventory.with_gpus(1, 4).to_dict()["nodes"][0],
                                                       "memory_bytes": 16 * GiB}]})
    entries = search(cfg, RUNNER_MODELS.get("embodied"), workload_of(cfg, _profile("embodied", costs)), inventory)
    assert entries and all(e.candidate.allocations["env"].ranks <= 2 for e in entries)
    assert max(e.memory_bytes for e in entries) <= 1.4 * gib + 1  # the device's, not the host's
    host = [reason for reason in entries.rejected if reason.startswith("over a node's host memory")]
    assert host == ["over a node's host memory: the smallest needs 24.50 GiB of 16.00 GiB"]  # 4 env ranks


def test_an_empty_search_names_the_reason_and_the_pinned_key(embodied):
    """env pinned on 3 slots with 16 envs: no depth splits them, whatever the other components do."""
    _, profile = embodied
    cfg = build_config("ppo_metaworld_reach", ["placement.env=0-2", "placement.rollout=auto",
                                               "placement.actor=auto", "env.num_envs=16"])[1]
    entries = search(cfg, RUNNER_MODELS.get("embodied"), workload_of(cfg, profile), ClusterInventory.cpu_only(1, 8))
    assert not entries
    assert entries.why_empty().startswith("env.num_envs=16 is not divisible by 3 env ranks (")
    assert entries.why_empty().endswith("with placement.env=0-2 (3 ranks) kept as written")
