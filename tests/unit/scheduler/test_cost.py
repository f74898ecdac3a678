"""The cost model against hand-computed cases and a slow event-by-event pipeline reference."""

import itertools
import random

import pytest

from infinirl.runtime import ClusterInventory, place
from infinirl.scheduler.cost import (
    Allocation,
    Candidate,
    Phase,
    WorkCost,
    Workload,
    memory_by_range,
    peak_device_memory,
    phase_seconds,
    predict,
    switch_seconds,
    time_sharing_groups,
)


def _on(first, count=1, ranks=None):
    return Allocation(first=first, count=count, ranks=count if ranks is None else ranks)


def _stream_workload(env_s=2.0, rollout_s=1.0, actor_s=0.5, hop_s=0.0, trips=0, overhead_s=0.0, **extra):
    """env -> rollout streamed, then an actor update; each cost is ``seconds`` for 1 unit on 1 rank."""
    costs = {"collect/env": WorkCost(per_unit_s=env_s, **extra), "collect/rollout": WorkCost(per_unit_s=rollout_s),
             "update/actor": WorkCost(per_unit_s=actor_s)}
    phases = (Phase(name="collect", components=("env", "rollout"), pipelined=True, round_trips=trips),
              Phase(name="update", components=("actor",)))
    return Workload(runner="t", phases=phases, units={"env": 1.0, "rollout": 1.0, "actor": 1.0}, costs=costs,
                    hop_s=hop_s, overhead_s=overhead_s)


def test_work_cost_seconds_and_memory_by_hand():
    cost = WorkCost(per_unit_s=0.01, fixed_s=0.1, comm_s=0.5, memory_fixed_bytes=100.0, memory_per_unit_bytes=2.0)
    assert cost.seconds(100, 1) == pytest.approx(0.1 + 1.0)
    assert cost.seconds(100, 2) == pytest.approx(0.1 + 0.5 + 0.5)
    assert cost.seconds(100, 8) == pytest.approx(0.1 + 0.125 + 1.5)
    assert cost.memory_bytes(100, 4) == pytest.approx(150.0)
    fast = cost.scaled(speedup=10, memory=0.5)
    assert fast.seconds(100, 2) == pytest.approx(0.11)
    assert fast.memory_bytes(100, 4) == pytest.approx(75.0)


def test_paced_work_takes_its_clock_time_on_any_device_and_leaves_the_device_to_others():
    """A robot at 0.05 s per step (its loop waits on the clock) beside a learner: on one slot the
    learner works while the robot waits, so the phase is the longer, not the sum; faster hardware
    speeds the learner up and never the robot's clock."""
    robot = WorkCost(per_unit_s=0.01, paced_per_unit_s=0.05)
    assert robot.seconds(50, 1) == pytest.approx(2.5) and robot.paced
    assert robot.scaled(speedup=100).seconds(50, 1) == pytest.approx(2.5)
    assert not WorkCost(per_unit_s=0.01).paced
    phase = Phase(name="iteration", components=("robot", "learner"), concurrent=True)
    for learner_s, expected in ((1.0, 2.5), (4.0, 4.0)):
        w = Workload(runner="t", phases=(phase,), units={"robot": 50.0, "learner": 1.0},
                     costs={"iteration/robot": robot, "iteration/learner": WorkCost(per_unit_s=learner_s)})
        for layout in ({"robot": _on(0), "learner": _on(0)}, {"robot": _on(0), "learner": _on(1)}):
            assert phase_seconds(w, phase, Candidate(allocations=layout)) == pytest.approx(expected)
    compute = {"iteration/robot": WorkCost(per_unit_s=0.05), "iteration/learner": WorkCost(per_unit_s=1.0)}
    w = Workload(runner="t", phases=(phase,), units={"robot": 50.0, "learner": 1.0}, costs=compute)
    shared = Candidate(allocations={"robot": _on(0), "learner": _on(0)})
    assert phase_seconds(w, phase, shared) == pytest.approx(3.5)  # compute-bound work on one slot adds up


def test_a_fixed_components_spec_is_written_as_given():
    cand = Candidate(allocations={"robot": _on(5), "learner": _on(1)}, fixed_specs={"robot": "robot:0"})
    assert cand.placement() == {"robot": "robot:0", "learner": "1"}


def test_time_sharing_sums_whatever_the_depth():
    w = _stream_workload(hop_s=1.0, trips=3)
    for depth in (1, 2, 4):
        cand = Candidate(allocations={"env": _on(0), "rollout": _on(0), "actor": _on(0)}, depth=depth)
        assert phase_seconds(w, w.phases[0], cand) == pytest.approx(3.0)  # 2 + 1, no hop in one process
        assert predict(w, cand).step_s == pytest.approx(3.5)


@pytest.mark.parametrize(("depth", "expected"), [(1, 3.0), (2, 1.5 + 1.0), (4, 0.75 + 1.5)])
def test_a_stream_that_passes_once_is_the_slowest_stage_plus_fill_and_drain(depth, expected):
    w = _stream_workload(hop_s=0.01, trips=0)
    cand = Candidate(allocations={"env": _on(0), "rollout": _on(1), "actor": _on(0)}, depth=depth)
    assert phase_seconds(w, w.phases[0], cand) == pytest.approx(expected)


@pytest.mark.parametrize(("depth", "expected"), [(1, 3.0 + 0.1), (2, max(2.0, 1.5 + 0.1)), (4, 2.0)])
def test_a_closed_loop_is_its_slowest_stage_or_one_chunks_way_round(depth, expected):
    """env 2 s and rollout 1 s over 10 round trips, 10 ms per message there and back: one chunk
    goes round in 3 s + 0.1 s; two chunks share the loop, which then waits on the env alone."""
    w = _stream_workload(hop_s=0.01, trips=10)
    cand = Candidate(allocations={"env": _on(0), "rollout": _on(1), "actor": _on(0)}, depth=depth)
    assert phase_seconds(w, w.phases[0], cand) == pytest.approx(expected)


def test_hybrid_groups_time_share_inside_and_pipeline_between():
    costs = {f"p/{c}": WorkCost(per_unit_s=s) for c, s in (("a", 1.0), ("b", 2.0), ("c", 4.0))}
    w = Workload(runner="t", phases=(Phase(name="p", components=("a", "b", "c"), pipelined=True),),
                 units={"a": 1.0, "b": 1.0, "c": 1.0}, costs=costs)
    cand = Candidate(allocations={"a": _on(0), "b": _on(0, 2), "c": _on(2)}, depth=2)
    assert time_sharing_groups(("a", "b", "c"), cand.allocations) == [["a", "b"], ["c"]]
    # b spans devices 0-1 with 2 ranks (1 s each) and shares device 0 with a: that group takes
    # 1 + 1 s, c 4 s; two chunks: (2 + 4) / 2 + 1/2 * 4
    assert phase_seconds(w, w.phases[0], cand) == pytest.approx(3.0 + 2.0)


def test_concurrent_phase_takes_the_longest_group():
    costs = {"p/x": WorkCost(per_unit_s=3.0), "p/y": WorkCost(per_unit_s=5.0)}
    w = Workload(runner="t", phases=(Phase(name="p", components=("x", "y"), concurrent=True),),
                 units={"x": 1.0, "y": 1.0}, costs=costs)
    apart = Candidate(allocations={"x": _on(0), "y": _on(1)})
    together = Candidate(allocations={"x": _on(0), "y": _on(0)})
    assert predict(w, apart).step_s == pytest.approx(5.0)
    assert predict(w, together).step_s == pytest.approx(8.0)


def test_ranks_stacked_on_a_device_take_turns():
    w = _stream_workload(actor_s=1.0)
    one = Candidate(allocations={"env": _on(0), "rollout": _on(0), "actor": _on(0)})
    stacked = Candidate(allocations={"env": _on(0), "rollout": _on(0), "actor": _on(0, 1, ranks=2)})
    assert _on(0, 1, ranks=2).spec() == "0:0-1"
    # two ranks of half the work each, one after the other on device 0: the same second
    assert predict(w, stacked).phases["update"] == pytest.approx(predict(w, one).phases["update"])


def test_switch_costs_only_for_components_that_time_share():
    w = _stream_workload(switch_s=0.25)  # the env's offload + reload
    shared = Candidate(allocations={"env": _on(0), "rollout": _on(1), "actor": _on(0)})
    alone = Candidate(allocations={"env": _on(0), "rollout": _on(1), "actor": _on(1)})
    assert switch_seconds(w, shared) == pytest.approx(0.25)
    assert switch_seconds(w, alone) == 0.0
    assert predict(w, shared).step_s == pytest.approx(predict(w, alone).step_s + 0.25)
    resident = Workload(runner="t", phases=w.phases, units=w.units, costs=w.costs, offloads=False)
    assert switch_seconds(resident, shared) == 0.0


def test_overhead_and_phases_add_up():
    w = _stream_workload(overhead_s=0.2)
    cand = Candidate(allocations={"env": _on(0), "rollout": _on(1), "actor": _on(0)}, depth=2)
    pred = predict(w, cand)
    assert pred.step_s == pytest.approx(sum(pred.phases.values()) + 0.2)


def test_memory_peak_by_hand():
    costs = {"collect/env": WorkCost(per_unit_s=1, memory_fixed_bytes=10.0),
             "collect/rollout": WorkCost(per_unit_s=1, memory_fixed_bytes=20.0, memory_per_unit_bytes=4.0),
             "update/actor": WorkCost(per_unit_s=1, memory_fixed_bytes=100.0)}
    w = _stream_workload()
    w = Workload(runner="t", phases=w.phases, units={"env": 1.0, "rollout": 2.0, "actor": 1.0}, costs=costs)
    cand = Candidate(allocations={"env": _on(0, 2), "rollout": _on(1, 2), "actor": _on(3)})
    # device 0: env 10; device 1: env 10 + rollout (20 + 4*2/2); device 2: rollout 24; device 3: actor 100
    assert peak_device_memory(w, cand) == pytest.approx(100.0)
    by_node = memory_by_range(w, cand, {0: range(0, 2), 1: range(2, 4)})
    assert by_node == {0: pytest.approx(44.0), 1: pytest.approx(124.0)}
    no_actor = Candidate(allocations={**cand.allocations, "actor": _on(0)})
    assert peak_device_memory(w, no_actor) == pytest.approx(110.0)


def test_bytes_cross_nodes_only_when_producer_and_consumer_are_apart():
    w = _stream_workload()
    w = Workload(runner="t", phases=w.phases, units=w.units, link_bytes_per_s=100.0,
                 costs={**w.costs, "collect/env": WorkCost(per_unit_s=2.0, bytes_out_per_unit=50.0)})
    node_of = lambda device: device // 2  # noqa: E731
    apart = Candidate(allocations={"env": _on(0), "rollout": _on(2), "actor": _on(0)})
    same = Candidate(allocations={"env": _on(0), "rollout": _on(1), "actor": _on(0)})
    assert phase_seconds(w, w.phases[0], apart, node_of) == pytest.approx(3.0 + 0.5)
    assert phase_seconds(w, w.phases[0], same, node_of) == pytest.approx(3.0)


def test_a_closed_loop_across_nodes_charges_the_way_back_too():
    """env -> rollout -> env (round trips): the env's observations go over the link and so do the
    rollout's actions; a stream that passes once (no round trips) sends nothing back."""
    w = _stream_workload(trips=3)
    costs = {**w.costs, "collect/env": WorkCost(per_unit_s=2.0, bytes_out_per_unit=50.0),
             "collect/rollout": WorkCost(per_unit_s=1.0, bytes_out_per_unit=20.0)}
    loop = Workload(runner="t", phases=w.phases, units=w.units, link_bytes_per_s=100.0, costs=costs)
    node_of = lambda device: device // 2  # noqa: E731
    apart = Candidate(allocations={"env": _on(0), "rollout": _on(2), "actor": _on(0)})
    same = Candidate(allocations={"env": _on(0), "rollout": _on(1), "actor": _on(0)})
    assert phase_seconds(loop, loop.phases[0], apart, node_of) == pytest.approx(3.0 + 0.5 + 0.2)
    assert phase_seconds(loop, loop.phases[0], same, node_of) == pytest.approx(3.0)
    once = _stream_workload()
    stream = Workload(runner="t", phases=once.phases, units=once.units, link_bytes_per_s=100.0, costs=costs)
    assert phase_seconds(stream, stream.phases[0], apart, node_of) == pytest.approx(3.0 + 0.5)


def test_host_memory_is_summed_per_node_apart_from_device_memory():
    costs = {"collect/env": WorkCost(per_unit_s=1, memory_fixed_bytes=1.0, host_memory_bytes=30.0),
             "collect/rollout": WorkCost(per_unit_s=1, memory_fixed_bytes=5.0, host_memory_bytes=10.0),
             "update/actor": WorkCost(per_unit_s=1, memory_fixed_bytes=7.0, host_memory_bytes=20.0)}
    w = _stream_workload()
    w = Workload(runner="t", phases=w.phases, units=w.units, costs=costs)
    cand = Candidate(allocations={"env": _on(0, 2), "rollout": _on(2), "actor": _on(3)})
    assert peak_device_memory(w, cand) == pytest.approx(7.0)
    nodes = {0: range(0, 2), 1: range(2, 4)}
    assert memory_by_range(w, cand, nodes, host=True) == {0: pytest.approx(60.0), 1: pytest.approx(30.0)}
    assert memory_by_range(w, cand, nodes) == {0: pytest.approx(2.0), 1: pytest.approx(12.0)}


def _pipeline_reference(stage_s: list[float], chunks: int) -> float:
    """Event by event, in float64: chunk j leaves stage i once stage i finished chunk j-1 and
    stage i-1 finished chunk j; every chunk takes 1/chunks of a stage's time."""
    done = [[0.0] * (chunks + 1) for _ in range(len(stage_s) + 1)]
    for i in range(1, len(stage_s) + 1):
        for j in range(1, chunks + 1):
            done[i][j] = max(done[i - 1][j], done[i][j - 1]) + stage_s[i - 1] / chunks
    return done[len(stage_s)][chunks]


def test_pipeline_formula_matches_an_event_by_event_reference():
    rng = random.Random(0)
    names = ("a", "b", "c", "d")
    for stages, depth in itertools.product((2, 3, 4), (1, 2, 3, 4, 8)):
        times = [rng.uniform(0.1, 5.0) for _ in range(stages)]
        comps = names[:stages]
        w = Workload(runner="t", phases=(Phase(name="p", components=comps, pipelined=True),),
                     units=dict.fromkeys(comps, 1.0),
                     costs={f"p/{c}": WorkCost(per_unit_s=t) for c, t in zip(comps, times)})
        cand = Candidate(allocations={c: _on(i) for i, c in enumerate(comps)}, depth=depth)
        assert phase_seconds(w, w.phases[0], cand) == pytest.approx(_pipeline_reference(times, depth), rel=1e-12)


def _loop_reference(stage_s: list[float], chunks: int, trips: int, hop_s: float) -> float:
    """Event by event, in float64: every chunk goes round the stages ``trips`` times; a stage takes
    the chunks in order, one at a time (1 / (chunks * trips) of its time each); each message
    between stages (the last stage back to the first included) is in flight hop_s / stages."""
    message = hop_s / len(stage_s)
    free = [0.0] * len(stage_s)
    back = [0.0] * chunks  # when each chunk's previous round trip left the last stage
    for trip in range(trips):
        for chunk in range(chunks):
            arrives = back[chunk] + (message if trip else 0.0)
            for i, seconds in enumerate(stage_s):
                free[i] = max(free[i], arrives) + seconds / (chunks * trips)
                arrives = free[i] + message
            back[chunk] = free[-1]
    return max(free)


def test_closed_loop_formula_is_within_3_percent_of_an_event_by_event_reference():
    """The formula leaves out one chunk's fill and drain, a share of one round trip: small once a
    chunk goes round 20 times or more (an embodied rollout: 100 env steps and more)."""
    rng = random.Random(0)
    names = ("a", "b", "c")
    for _ in range(300):
        stages, depth = rng.choice((2, 3)), rng.choice((1, 2, 3, 4, 8))
        trips, hop = rng.choice((20, 50, 101)), rng.uniform(0.0, 0.05)
        times = [rng.uniform(0.1, 5.0) for _ in range(stages)]
        comps = names[:stages]
        w = Workload(runner="t", phases=(Phase(name="p", components=comps, pipelined=True, round_trips=trips),),
                     units=dict.fromkeys(comps, 1.0), hop_s=hop,
                     costs={f"p/{c}": WorkCost(per_unit_s=t) for c, t in zip(comps, times)})
        cand = Candidate(allocations={c: _on(i) for i, c in enumerate(comps)}, depth=depth)
        assert phase_seconds(w, w.phases[0], cand) == pytest.approx(_loop_reference(times, depth, trips, hop),
                                                                     rel=0.03)


def test_allocation_specs_are_what_place_accepts():
    inventory = ClusterInventory.with_gpus(2, 4)
    specs = {"a": _on(0).spec(), "b": _on(2, 4).spec(), "c": _on(0, 2, ranks=4).spec(), "d": _on(4, 4, ranks=2).spec()}
    assert specs == {"a": "0", "b": "2-5", "c": "0-1:0-3", "d": "4-7:0-1"}
    plan = place(inventory, specs)
    assert plan.world_size("c") == 4 and plan.world_size("d") == 2
    assert plan.devices_of("b") == (2, 3, 4, 5)


def test_predict_names_a_missing_component():
    w = _stream_workload()
    with pytest.raises(ValueError, match="actor"):
        predict(w, Candidate(allocations={"env": _on(0), "rollout": _on(0)}))
