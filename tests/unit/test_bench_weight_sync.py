"""benchmarks/weight_sync.py's run order and paired ratios: the two modes alternate which runs first
(a machine drifting over the runs would otherwise always favour one), and each repeat's two
back-to-back runs give a ratio of their own."""

import os
import sys

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import weight_sync as bench  # noqa: E402


def test_the_modes_alternate_which_runs_first():
    assert [bench.mode_order(r) for r in range(3)] == [("changed_only", "full"), ("full", "changed_only"),
                                                        ("changed_only", "full")]


def test_each_repeat_gives_full_over_changed_only_of_its_own_runs_after_the_first_iteration():
    changed = [{"sync_s": [9.0, 1.0, 1.0, 2.0], "step_s": [30.0, 10.0, 10.0, 11.0]},
               {"sync_s": [9.0, 2.0, 2.0, 2.0], "step_s": [30.0, 20.0, 20.0, 20.0]}]  # a slow spell
    full = [{"sync_s": [9.0, 3.0, 3.0, 3.0], "step_s": [30.0, 12.0, 12.0, 12.0]},
            {"sync_s": [9.0, 6.0, 6.0, 6.0], "step_s": [30.0, 24.0, 24.0, 24.0]}]
    assert bench.repeat_ratios(changed, full) == {"weight_sync_changed_vs_full": [3.0, 3.0],
                                                  "step_changed_vs_full": [1.2, 1.2]}
