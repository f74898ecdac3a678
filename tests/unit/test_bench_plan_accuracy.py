"""benchmarks/plan_accuracy.py's summary: ratios, the share within 20%, and the chosen placement
against the best hand-written one, both as a flag and as a ratio (a 1% loss reads as one)."""

import os
import sys

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import plan_accuracy as bench  # noqa: E402


def test_summary_of_one_job():
    placements = {
        "a": {"role": "hand-written: collocated (default)", "ratio": 1.02, "measured_s": 11.2},
        "b": {"role": "hand-written: disaggregated", "ratio": 1.25, "measured_s": 11.4},
        "c": {"role": "chosen", "ratio": 0.99, "measured_s": 11.312},
        "d": {"role": "ranked", "ratio": 0.86, "measured_s": 13.0},
    }
    summary = bench.summarise({"reasoning": {"placements": placements}})
    assert summary["ratios"]["reasoning/c"] == 0.99
    assert summary["within_20pct"] == {"reasoning": 0.75}
    assert summary["chosen_no_slower"] == {"reasoning": False}
    # seconds over seconds: above 1, the chosen placement is the slower one
    assert summary["chosen_s_over_best_hand_written_s"] == {"reasoning": 1.01}
    assert "chosen_vs_best_hand_written" not in summary
