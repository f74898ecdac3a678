"""Benchmark: the main GRPO job synchronous vs asynchronous (max_staleness 1 and 2), side by side.

Each row runs `infinirl train grpo_arithmetic` (SmolLM2-135M, one-operation arithmetic, 8 prompts x 8
samples a step) for ``--iterations`` iterations in its own subprocess, same seed, data and number of
samples; only ``algorithm.asynchronous.max_staleness`` (and, for the asynchronous rows, the
off-policy correction ``algorithm.objective.is_cap=2, is_cap_mode=mask`` and the torch threads per
worker, ``--async-threads``) differ. Reported per row: training throughput (samples / the summed
step times; evaluation excluded), median seconds per step, the held-out greedy accuracy at every
evaluation, and the training time until the held-out accuracy first reaches the synchronous run's
final one.

    python benchmarks/async_vs_sync.py                       # the full job: 40 iterations a row
    python benchmarks/async_vs_sync.py --iterations 6 --rows sync,eta1   # a quick look

Last stdout line: {"benchmark": "async_vs_sync", "ratios": {"grpo_async_vs_sync": sync s/sample /
eta=1 s/sample, "grpo_async2_vs_sync": the same for eta=2}, "accuracy_gap": {row: sync final -
row final, in points}, "targets": ..., "results": {...}}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

from _bench_common import add_record_argument, record_result

ROWS = {  # name -> max_staleness (None: the synchronous loop)
    "sync": None,
    "eta1": 1,
    "eta2": 2,
}
RATIO_KEYS = {"eta1": "grpo_async_vs_sync", "eta2": "grpo_async2_vs_sync"}
TARGETS = {"grpo_async_vs_sync": 1.5}
CORRECTION = ["algorithm.objective.is_cap=2.0", "algorithm.objective.is_cap_mode=mask"]


def overrides(row: str, iterations: int, eval_every: int, out: str, async_threads: tuple[int, int]) -> list[str]:
    args = [f"iterations={iterations}", f"eval.every={eval_every}", f"output_dir={out}", "resume=false",
            "loggers=[]", "save_every=100000", "cluster.log_to_driver=false"]
    eta = ROWS[row]
    if eta is not None:
        actor_threads, rollout_threads = async_threads
        args += [f"algorithm.asynchronous.max_staleness={eta}", *CORRECTION,
                 f"num_threads={actor_threads}", f"rollout.num_threads={rollout_threads}"]
    return args


def summarise(out: str) -> dict:
    rows = [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl"))]
    steps = [r for r in rows if "time/step_s" in r]
    evals = [r for r in rows if "eval/greedy_accuracy" in r]
    train_s, clock, curve = 0.0, {}, []
    for r in rows:  # training time (summed step times) at each evaluation
        if "time/step_s" in r:
            train_s += r["time/step_s"]
            clock[r["step"]] = train_s
    for r in evals:
        curve.append({"step": r["step"], "train_s": round(clock.get(r["step"], 0.0), 1),
                      "accuracy": r["eval/greedy_accuracy"]})
    return {
        "iterations": len(steps),
        "train_s": round(train_s, 1),
        "median_step_s": round(statistics.median(r["time/step_s"] for r in steps[1:] or steps), 2),
        "staleness_mean": statistics.mean(r.get("async/staleness_mean", 0.0) for r in steps),
        "eval": curve,
        "final_accuracy": curve[-1]["accuracy"] if curve else None,
    }


def time_to(curve: list[dict], accuracy: float) -> float | None:
    """Training seconds until the held-out accuracy first reaches ``accuracy``."""
    return next((point["train_s"] for point in curve if point["accuracy"] >= accuracy - 1e-9), None)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--eval-every", type=int, default=5)
    parser.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated, from {', '.join(ROWS)}")
    parser.add_argument("--async-threads", default="1,1",
                        help="torch threads of the actor and of the rollout in the asynchronous rows (they run at "
                             "the same time; the synchronous row keeps the job's 2 and 2, used one after the other)")
    add_record_argument(parser)
    args = parser.parse_args()
    wanted = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = sorted(set(wanted) - set(ROWS))
    if unknown:
        parser.error(f"--rows: unknown {unknown}; choose from {', '.join(ROWS)}")
    async_threads = tuple(int(x) for x in args.async_threads.split(","))
    results = {}
    for row in wanted:
        out = tempfile.mkdtemp(prefix=f"bench-async-{row}-")
        command = [sys.executable, "-m", "infinirl.cli", "train", "grpo_arithmetic",
                   *overrides(row, args.iterations, args.eval_every, out, async_threads)]
        start = time.perf_counter()
        proc = subprocess.run(command, capture_output=True, text=True)
        if proc.returncode:
            results[row] = {"failed": f"exit {proc.returncode}: {proc.stderr[-1500:]}"}
        else:
            results[row] = summarise(out)
        results[row]["wall_s"] = round(time.perf_counter() - start, 1)
        results[row]["command"] = " ".join(command[2:])
        print(f"[{row}] {json.dumps(results[row])[:600]}", file=sys.stderr, flush=True)

    sync = results.get("sync", {})
    ratios, gaps, to_target = {}, {}, {}
    for row, key in RATIO_KEYS.items():
        res = results.get(row, {})
        if sync.get("train_s") and res.get("train_s"):
            ratios[key] = round(sync["train_s"] / res["train_s"], 3)  # same samples: throughput ratio
    for row, res in results.items():
        if sync.get("final_accuracy") is not None and res.get("final_accuracy") is not None:
            gaps[row] = round(100 * (sync["final_accuracy"] - res["final_accuracy"]), 1)
            to_target[row] = time_to(res["eval"], sync["final_accuracy"])
    final = {"benchmark": "async_vs_sync", "ratios": ratios, "targets": TARGETS,
             "accuracy_gap_points": gaps, "train_s_to_sync_final_accuracy": to_target,
             "device": f"{platform.processor() or platform.machine()} ({os.cpu_count()} cpus)",
             "iterations": args.iterations, "async_threads": list(async_threads), "results": results}
    print(json.dumps(final))
    record_result(args.record, "Asynchronous vs synchronous GRPO", final)
    return 0


if __name__ == "__main__":
    sys.exit(main())
