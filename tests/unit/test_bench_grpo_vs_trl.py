"""benchmarks/grpo_vs_trl.py's step statistics, ratios and failures: the first step (warm-up) is
never measured, the asynchronous row's last (no next batch generated beside its update) neither,
and a row that failed or computed in another dtype fails the run instead of leaving a null ratio."""

import os
import sys

import pytest

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import grpo_vs_trl as bench  # noqa: E402

FP32 = {"actor": "float32", "rollout": "float32"}


def test_the_first_step_and_the_asynchronous_rows_last_are_not_measured():
    steps = [90.0, 40.0, 41.0, 39.0, 29.0]
    assert bench.measured_steps(steps, asynchronous=False) == [40.0, 41.0, 39.0, 29.0]
    assert bench.measured_steps(steps, asynchronous=True) == [40.0, 41.0, 39.0]
    with pytest.raises(ValueError, match="--steps >= 5"):
        bench.measured_steps(steps[:4], asynchronous=True)


def test_a_failed_row_leaves_its_ratios_null_and_fails_the_run():
    results = {"infinirl": {"median_step_s": 40.0, "dtype": FP32}, "trl": {"failed": "exit 1: ImportError"},
               "infinirl_async": {"median_step_s": 32.0, "dtype": FP32}}
    ratios = bench.speed_ratios(results)
    assert ratios == {"step_speed_vs_trl": None, "step_speed_vs_trl_async": None, "step_speed_async_vs_sync": 1.25}
    assert bench.row_failures(results, "float32") == ["trl: exit 1: ImportError"]


def test_a_row_in_another_dtype_than_the_one_given_fails_the_run():
    results = {"infinirl": {"median_step_s": 40.0, "dtype": FP32},
               "trl": {"median_step_s": 80.0, "dtype": {"actor": "bfloat16", "rollout": "bfloat16"}}}
    assert bench.speed_ratios(results)["step_speed_vs_trl"] == 2.0
    assert bench.row_failures(results, "float32") == [
        "trl: ran in {'actor': 'bfloat16', 'rollout': 'bfloat16'}, not float32 like the other rows"]
