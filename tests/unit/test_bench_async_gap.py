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


def _write_metrics(folder, rows):
    import json

    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_training_time_counts_the_wait_for_batches_in_flight_before_an_evaluation(tmp_path):
    """An asynchronous run's evaluation queues behind the batches already submitted; the wait for
    them (time/eval_drain_s) is generation that belongs to training, the evaluation itself is not."""
    _write_metrics(tmp_path, [
        {"step": 0, "eval/greedy_accuracy": 0.25, "time/eval_s": 9.0, "time/eval_drain_s": 0.0},
        {"step": 1, "time/step_s": 10.0},
        {"step": 2, "time/step_s": 10.0, "eval/greedy_accuracy": 0.5, "time/eval_s": 9.0, "time/eval_drain_s": 4.0},
        {"step": 3, "time/step_s": 6.0},
        {"step": 4, "time/step_s": 10.0, "eval/greedy_accuracy": 0.75, "time/eval_s": 9.0, "time/eval_drain_s": 0.0},
    ])
    summary = bench.summarise(bench.JOBS["grpo"], str(tmp_path))
    assert summary["train_s"] == 40.0 and summary["eval_drain_s"] == 4.0
    assert [p["train_s"] for p in summary["eval"]] == [0.0, 24.0, 40.0]


def test_throughput_ratio_is_the_mean_of_per_seed_ratios_with_their_spread():
    sync = {1: {"train_s": 100.0}, 2: {"train_s": 300.0}}  # seed 2's rows ran in a slow spell
    row = {1: {"train_s": 50.0}, 2: {"train_s": 250.0}}
    spread = bench.seed_ratios(sync, row)
    assert spread["per_seed"] == {"1": 2.0, "2": 1.2}
    assert spread["mean"] == 1.6 and (spread["min"], spread["max"]) == (1.2, 2.0)
    assert math.isclose(spread["sd"], round(math.sqrt(0.32), 3))
    # a summed time would let the slow seed dominate: 400 / 300 = 1.33
    assert bench.seed_ratios({None: {"train_s": 10.0}}, {None: {"train_s": 8.0}})["sd"] is None
    assert bench.seed_ratios(sync, {1: {"train_s": 50.0}, 2: {"failed": "exit 1"}}) is None


def test_the_overlap_ceiling_is_twice_the_synchronous_time_over_the_one_thread_each_time():
    """Asynchronous rows run a step's work side by side on two cores, one thread each: a step takes at
    least half the work on one core, so 2 x sync / sync1 bounds any asynchronous speed-up."""
    sync = {None: {"train_s": 30.0}}
    one_thread_each = {None: {"train_s": 48.0}}
    assert bench.seed_ratios(sync, one_thread_each, scale=2.0)["mean"] == 1.25
    assert bench.ROWS["sync1"].ratio_key("grpo") == "grpo_overlap_ceiling"


def test_the_one_thread_each_row_is_synchronous_with_the_asynchronous_rows_threads():
    args = bench.overrides(bench.JOBS["grpo"], "sync1", 5, "/tmp/out", (1, 1))
    assert "num_threads=1" in args and "rollout.num_threads=1" in args
    assert not any(a.startswith("algorithm.asynchronous") for a in args)
    assert "sync1" not in bench.DEFAULT_ROWS
