"""The asynchronous benchmark's held-out gap over seeds (benchmarks/async_vs_sync.py).

Why: one seed's final held-out accuracy moves by several points between neighbouring evaluations,
so a gap over a few seeds means little without its standard error; the summary must report both,
computed from the per-seed paired differences (each seed's rows share the held-out questions)."""

import math
import os
import sys

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import async_vs_sync as bench  # noqa: E402


def test_gap_is_the_mean_paired_difference_in_points_with_its_standard_error():
    pairs = [(0.859, 0.812), (0.828, 0.812), (0.781, 0.734)]
    diffs = [100 * (a - b) for a, b in pairs]
    mean = sum(diffs) / 3
    sd = math.sqrt(sum((d - mean) ** 2 for d in diffs) / 2)  # sample standard deviation
    summary = bench.paired_gap(pairs)
    assert summary["seeds"] == 3
    assert math.isclose(summary["mean"], round(mean, 1))
    assert math.isclose(summary["se"], round(sd / math.sqrt(3), 1))


def test_one_seed_has_a_gap_but_no_standard_error():
    assert bench.paired_gap([(0.8, 0.75)]) == {"mean": 5.0, "se": None, "seeds": 1}


def test_a_row_ahead_of_the_synchronous_run_has_a_negative_gap():
    assert bench.paired_gap([(0.75, 0.8), (0.75, 0.8)])["mean"] == -5.0
