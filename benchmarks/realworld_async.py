"""Benchmark: the same SAC learner on a simulated robot in real time, synchronous vs asynchronous.

Both runs are the ``realworld_sac`` runner with the config ``--config`` (default: the Sawyer reach
at 20 Hz, state-based SAC), the same seed, learner and robot, for ``--seconds`` of training
wall-clock time each (``--iteration-s`` windows; start-up and the final evaluation not counted):

  sync:   collect one episode, then ``algorithm.utd_ratio`` updates per collected step, then send
          the weights (the robot idles while the learner updates, the learner while the robot acts);
  async:  the robot acts at its own rate with the newest weights it has and streams episodes; the
          learner stores them and updates continuously (``pipeline.mode=async``).

Measured per run, from its ``metrics.jsonl``: learner updates per wall-clock second of training
(all updates / the summed iteration windows, warm-up included in both), the time until the
training episodes' success rate within one window first reached ``--success`` (null when it did
not within the budget), the final deterministic evaluation's success rate, and the staleness the
asynchronous run saw.

    python benchmarks/realworld_async.py                  # 2 x 60 s of training, a few minutes in all
    python benchmarks/realworld_async.py --seconds 300    # long enough for both to learn the reach
    python benchmarks/realworld_async.py demos.episodes=10   # config overrides apply to both runs (RLPD here)

The last stdout line is ONE JSON object: {"benchmark": "realworld_async", "ratios":
{"async_vs_sync_updates": async updates/s / sync updates/s}, "targets": {...}, "results": {...}}.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import add_record_argument, conclude, concluded, device_description  # noqa: E402

TARGETS = {"async_vs_sync_updates": 5.0}


def run_mode(config: str, mode: str, args, folder: str) -> dict:
    from infinirl.cli import build_config
    from infinirl.runners.realworld_sac import run

    iterations = max(1, math.ceil(args.seconds / args.iteration_s))
    output = os.path.join(folder, mode)
    overrides = [f"pipeline.mode={mode}", f"iterations={iterations}", f"pipeline.iteration_s={args.iteration_s}",
                 f"output_dir={output}", "loggers=[]", "save_every=0", "keep_checkpoints=1", "eval.every=0",
                 f"eval.episodes={args.eval_episodes}", f"seed={args.seed}", "cluster.log_to_driver=false"]
    _, cfg = build_config(config, [*overrides, *args.overrides])
    cfg.validate()
    summary = run(cfg)
    with open(os.path.join(output, "metrics.jsonl")) as handle:
        rows = [json.loads(line) for line in handle]
    train_s = sum(row.get("time/iteration_s", 0.0) for row in rows)
    reached, elapsed = None, 0.0
    for row in rows:
        elapsed += row.get("time/iteration_s", 0.0)
        if reached is None and row.get("rollout/success_rate", 0.0) >= args.success:
            reached = round(elapsed, 1)
    last = rows[-1]
    updates = last["train/updates"]  # logged at the end of the last window, before the final evaluation
    return {"updates": updates, "train_s": round(train_s, 1), "updates_per_s": round(updates / max(train_s, 1e-9), 2),
            "env_steps": last.get("env/steps"), "replay_transitions": summary["replay_transitions"],
            "time_to_success_s": reached, "final_eval_success_rate": last.get("eval/success_rate"),
            "last_window_success_rate": last.get("rollout/success_rate"),
            "staleness_mean": last.get("pipeline/staleness_mean"), "staleness_max": last.get("pipeline/staleness_max"),
            "late_robot_steps": last.get("robot/late_steps")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="realworld_sac_sawyer_reach")
    parser.add_argument("--seconds", type=float, default=60.0, help="training wall-clock seconds per mode")
    parser.add_argument("--iteration-s", type=float, default=10.0)
    parser.add_argument("--success", type=float, default=0.8, help="training success rate of 'time to success'")
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("overrides", nargs="*", help="config overrides for both runs, e.g. demos.episodes=10")
    parser.add_argument("--dir", default=None, help="folder for the runs (default: a temporary one, removed)")
    add_record_argument(parser)
    args = parser.parse_args()
    from infinirl.runtime import Cluster

    folder = args.dir or tempfile.mkdtemp(prefix="bench-realworld-")
    started = time.perf_counter()
    try:
        with Cluster(log_to_driver=False):  # one Ray instance for both runs
            results = {mode: run_mode(args.config, mode, args, folder) for mode in ("sync", "async")}
    finally:
        if args.dir is None:
            shutil.rmtree(folder, ignore_errors=True)
    ratio = results["async"]["updates_per_s"] / max(results["sync"]["updates_per_s"], 1e-9)
    final = {"benchmark": "realworld_async", "ratios": {"async_vs_sync_updates": round(ratio, 2)},
             "targets": TARGETS, "results": results,
             "settings": {"config": args.config, "seconds_per_mode": args.seconds, "iteration_s": args.iteration_s,
                          "success_threshold": args.success, "seed": args.seed},
             "device": device_description(), "elapsed_s": round(time.perf_counter() - started, 1)}
    return conclude(final, record=(args.record, "Real-world SAC: asynchronous vs synchronous"))


if __name__ == "__main__":
    sys.exit(concluded("realworld_async", main))
