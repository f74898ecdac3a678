"""Benchmark: the main job's weight sync, changed-only against full, side by side.

`infinirl train grpo_arithmetic` (SmolLM2-135M, LoRA on the top 10 of 30 layers, hf rollout engine)
for ``--iterations`` iterations with ``rollout.sync_changed_only`` true (after the first sync only
the merged adapted layers go to the rollout) and false (every weight every time), in that order
``--repeats`` times, each run in its own subprocess, evaluation off. Reported per mode: the median
of ``time/weight_sync_s`` and of ``time/step_s`` over the iterations after the first (whose sync is
full in both modes), pooled over the repeats. The runs should learn the same (a changed-only sync
leaves the rollout's model the trainer's): ``same_rewards`` says whether their rewards per step are
equal, and the script exits 1 when they are not.

    python benchmarks/weight_sync.py                       # 5 iterations, 2 repeats
    python benchmarks/weight_sync.py --iterations 3 --repeats 1 --set actor.lr=2e-4

Last stdout line: {"benchmark": "weight_sync", "ratios": {"weight_sync_changed_vs_full": full's median
sync seconds / changed-only's, "step_changed_vs_full": the same for the whole step}, "same_rewards": bool,
"results": {mode: {...}}}.
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

from _bench_common import add_record_argument, record_result

MODES = {"changed_only": "rollout.sync_changed_only=true", "full": "rollout.sync_changed_only=false"}


def one_run(mode: str, iterations: int, extra: list[str]) -> dict:
    out = tempfile.mkdtemp(prefix=f"bench-weight-sync-{mode}-")
    command = [sys.executable, "-m", "infinirl.cli", "train", "grpo_arithmetic", f"iterations={iterations}",
               f"output_dir={out}", "resume=false", "loggers=[]", "save_every=0", "eval.every=0",
               "eval.at_start=false", "cluster.log_to_driver=false", MODES[mode], *extra]
    proc = subprocess.run(command, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"{mode}: exit {proc.returncode}: {proc.stderr[-2000:]}")
    rows = [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl"))]
    steps = [r for r in rows if "time/step_s" in r]
    return {"sync_s": [r["time/weight_sync_s"] for r in steps], "step_s": [r["time/step_s"] for r in steps],
            "rewards": [r["rollout/reward_mean"] for r in steps], "command": "infinirl " + " ".join(command[3:])}


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
    runs: dict[str, list[dict]] = {mode: [] for mode in MODES}
    for repeat in range(args.repeats):
        for mode in MODES:
            runs[mode].append(one_run(mode, args.iterations, args.extra))
            print(f"[{mode} {repeat}] {json.dumps(runs[mode][-1])[:400]}", file=sys.stderr, flush=True)
    results = {}
    for mode, done in runs.items():
        later_sync = [s for run in done for s in run["sync_s"][1:]]
        later_step = [s for run in done for s in run["step_s"][1:]]
        results[mode] = {"median_sync_s": round(statistics.median(later_sync), 3),
                         "median_step_s": round(statistics.median(later_step), 2),
                         "first_sync_s": [round(run["sync_s"][0], 3) for run in done],
                         "runs": done}
    changed, full = results["changed_only"], results["full"]
    final = {"benchmark": "weight_sync",
             "ratios": {"weight_sync_changed_vs_full": round(full["median_sync_s"] / changed["median_sync_s"], 3),
                        "step_changed_vs_full": round(full["median_step_s"] / changed["median_step_s"], 3)},
             "same_rewards": all(a["rewards"] == b["rewards"] for a, b in zip(runs["changed_only"], runs["full"])),
             "device": f"{platform.processor() or platform.machine()} ({os.cpu_count()} cpus)",
             "iterations": args.iterations, "repeats": args.repeats, "results": results}
    print(json.dumps(final))
    record_result(args.record, "Weight sync: changed-only against full", final)
    return 0 if final["same_rewards"] else 1


if __name__ == "__main__":
    sys.exit(main())
