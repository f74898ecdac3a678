"""Benchmark: the main job's weight sync, changed-only against full, side by side.

`infinirl train grpo_arithmetic` (SmolLM2-135M, LoRA on the top 10 of 30 layers, hf rollout engine)
for ``--iterations`` iterations with ``rollout.sync_changed_only`` true (after the first sync only
the merged adapted layers go to the rollout) and false (every weight every time), ``--repeats``
times, each run in its own subprocess, evaluation off. The two modes run back to back, changed-only
first in even repeats and full first in odd ones, so a machine whose speed drifts over the runs
weighs on both alike. Reported per mode: the median of ``time/weight_sync_s`` and of
``time/step_s`` over the iterations after the first (whose sync is full in both modes), pooled over
the repeats; and per repeat the paired ratios of its two back-to-back runs. The runs should learn
the same (a changed-only sync leaves the rollout's model the trainer's): ``same_rewards`` says
whether their rewards per step are equal.

    python benchmarks/weight_sync.py                       # 5 iterations, 2 repeats
    python benchmarks/weight_sync.py --iterations 3 --repeats 1 --set actor.lr=2e-4

Last stdout line: {"benchmark": "weight_sync", "ratios": {"weight_sync_changed_vs_full": full's median
sync seconds / changed-only's, "step_changed_vs_full": the same for the whole step}, "per_repeat":
{ratio key: [each repeat's ratio]}, "order": [each repeat's modes in run order], "same_rewards": bool,
"results": {mode: {...}}, "failures": [...]}. A failed run or rewards that differ between the modes
are listed in "failures" and the script exits 1.
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

from _bench_common import add_record_argument, conclude, concluded, failures_of, side_failed

MODES = {"changed_only": "rollout.sync_changed_only=true", "full": "rollout.sync_changed_only=false"}
RATIOS = {"weight_sync_changed_vs_full": "sync_s", "step_changed_vs_full": "step_s"}


def one_run(mode: str, iterations: int, extra: list[str]) -> dict:
    out = tempfile.mkdtemp(prefix=f"bench-weight-sync-{mode}-")
    command = [sys.executable, "-m", "infinirl.cli", "train", "grpo_arithmetic", f"iterations={iterations}",
               f"output_dir={out}", "resume=false", "loggers=[]", "save_every=0", "eval.every=0",
               "eval.at_start=false", "cluster.log_to_driver=false", MODES[mode], *extra]
    proc = subprocess.run(command, capture_output=True, text=True)
    if proc.returncode:
        return side_failed(f"exit {proc.returncode}: {proc.stderr[-2000:]}")
    rows = [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl"))]
    steps = [r for r in rows if "time/step_s" in r]
    return {"sync_s": [r["time/weight_sync_s"] for r in steps], "step_s": [r["time/step_s"] for r in steps],
            "rewards": [r["rollout/reward_mean"] for r in steps], "command": "infinirl " + " ".join(command[3:])}


def mode_order(repeat: int) -> tuple[str, ...]:
    """The modes of one repeat in run order: changed-only first in even repeats, full first in odd ones."""
    order = tuple(MODES)
    return order if repeat % 2 == 0 else order[::-1]


def repeat_ratios(changed: list[dict], full: list[dict]) -> dict[str, list[float]]:
    """Per repeat, of its two back-to-back runs: full's median over changed-only's (iterations after the
    first), of the weight sync and of the whole step."""
    def median_later(run: dict, key: str) -> float:
        return statistics.median(run[key][1:])

    return {ratio: [round(median_later(f, key) / median_later(c, key), 3) for c, f in zip(changed, full)]
            for ratio, key in RATIOS.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--set", dest="extra", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for every run (repeatable)")
    add_record_argument(parser)
    args = parser.parse_args()
    if args.iterations < 2:
        parser.error("--iterations: at least 2 (the first sync is full in both modes)")
    if args.repeats < 1:
        parser.error("--repeats: at least 1")
    runs: dict[str, list[dict]] = {mode: [] for mode in MODES}
    order, failed = [], {}
    for repeat in range(args.repeats):
        order.append(mode_order(repeat))
        for mode in order[-1]:
            run = one_run(mode, args.iterations, args.extra)
            print(f"[{mode} {repeat}] {json.dumps(run)[:400]}", file=sys.stderr, flush=True)
            if "failed" in run:
                failed[mode] = run
                break
            runs[mode].append(run)
        if failed:  # the other runs would fail alike: stop, and say so
            break
    final = {"benchmark": "weight_sync", "ratios": {key: None for key in RATIOS}, "per_repeat": {}, "order": order,
             "same_rewards": None, "device": f"{platform.processor() or platform.machine()} ({os.cpu_count()} cpus)",
             "iterations": args.iterations, "repeats": args.repeats}
    if failed:
        return conclude({**final, "results": {**{m: {"runs": r} for m, r in runs.items()}, **failed}},
                        failures_of(failed))
    results = {}
    for mode, done in runs.items():
        results[mode] = {"median_sync_s": round(statistics.median(s for run in done for s in run["sync_s"][1:]), 3),
                         "median_step_s": round(statistics.median(s for run in done for s in run["step_s"][1:]), 2),
                         "first_sync_s": [round(run["sync_s"][0], 3) for run in done],
                         "runs": done}
    changed, full = results["changed_only"], results["full"]
    same = [a["rewards"] == b["rewards"] for a, b in zip(runs["changed_only"], runs["full"])]
    final.update({"ratios": {"weight_sync_changed_vs_full": round(full["median_sync_s"] / changed["median_sync_s"], 3),
                             "step_changed_vs_full": round(full["median_step_s"] / changed["median_step_s"], 3)},
                  "per_repeat": repeat_ratios(runs["changed_only"], runs["full"]), "same_rewards": all(same),
                  "results": results})
    failures = [f"same work: the rewards per step differ between the modes in repeat {r}"
                for r, equal in enumerate(same) if not equal]
    return conclude(final, failures, record=(args.record, "Weight sync: changed-only against full"))


if __name__ == "__main__":
    sys.exit(concluded("weight_sync", main))
