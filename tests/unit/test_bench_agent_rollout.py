"""benchmarks/agent_rollout.py's order and ratio: the rows alternate which runs first (the first
one always ran first before, on an engine without a warm-up), and each repeat's back-to-back runs
give a ratio of their own, the reported one being their median."""

import os
import sys

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import agent_rollout as bench  # noqa: E402


def test_the_rows_alternate_which_runs_first():
    assert [bench.row_order(["lockstep", "async"], r) for r in range(3)] == [
        ["lockstep", "async"], ["async", "lockstep"], ["lockstep", "async"]]


def test_the_ratio_is_the_median_of_the_per_repeat_ratios():
    runs = {"lockstep": [{"trajectories_per_s": 2.0}, {"trajectories_per_s": 1.0}, {"trajectories_per_s": 2.0}],
            "async": [{"trajectories_per_s": 6.0}, {"trajectories_per_s": 2.5}, {"trajectories_per_s": 4.0}]}
    results, per_repeat, ratios = bench.summarise_runs(runs)
    assert per_repeat == {"agent_async_vs_lockstep": [3.0, 2.5, 2.0]}
    assert ratios == {"agent_async_vs_lockstep": 2.5}
    assert results["async"]["trajectories_per_s"] == 4.0 and len(results["async"]["runs"]) == 3
    assert bench.summarise_runs({"async": runs["async"]})[2] == {}
