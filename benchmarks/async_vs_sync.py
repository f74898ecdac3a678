"""Benchmark: synchronous vs asynchronous training (max_staleness 1, 2, 1 with partial rollouts), side by side.

Two jobs (``--jobs``):

* ``grpo``: the main job, `infinirl train grpo_arithmetic` (SmolLM2-135M, one-operation arithmetic,
  8 prompts x 8 samples a step); asynchronous rows add decoupled PPO
  (``algorithm.objective.is_cap=2, is_cap_mode=mask``) and give the actor and the rollout
  ``--async-threads`` torch threads each (they now run at the same time);
* ``ppo``: the MetaWorld PPO demo, `infinirl train ppo_metaworld_reach` (16 envs x 100 steps an
  iteration, collocated placement); asynchronous rows add ``algorithm.is_cap=2``.

Each row runs in its own subprocess for ``--iterations`` iterations (default: the shipped
config's), same seed, data and number of samples; only ``algorithm.asynchronous.max_staleness`` and
the settings above differ. Reported per row: training time and so throughput, median seconds per
iteration, the held-out metric at every evaluation, and the training time until it first reaches the
synchronous run's final value. Training time = the summed iteration times plus, in asynchronous rows,
the wait for the batches in flight before each evaluation (``time/eval_drain_s``): an evaluation's
requests queue behind them on the rollout side, and their generation belongs to training; the
evaluation itself is excluded.

    python benchmarks/async_vs_sync.py                                   # both jobs, full length
    python benchmarks/async_vs_sync.py --jobs grpo --iterations 6 --rows sync,eta1   # a quick look
    python benchmarks/async_vs_sync.py --jobs grpo --rows sync,eta1 --seeds 1,2,3    # accuracy over seeds
    python benchmarks/async_vs_sync.py --jobs grpo --rows sync,eta1 --set actor.lr_schedule=cosine \
        --set actor.total_steps=40 --set actor.min_lr_ratio=0.1                   # both rows changed alike

Row ``sync1`` (not run by default) is the synchronous loop with the asynchronous rows' threads
(``--async-threads``, one each): the whole work of a step on one core. The asynchronous rows run the
same work on two cores side by side, so, whatever the overlap, a step cannot take less than half of
it: ``grpo_overlap_ceiling`` = 2 x sync training time / sync1's is the most any asynchronous row can
gain over the synchronous one on this host (about 2 where neither half of the step gains from a
second thread, about 1 where both scale perfectly to two).

    python benchmarks/async_vs_sync.py --jobs grpo --rows sync,sync1,eta1 --iterations 5   # ceiling vs got

With ``--seeds``, every row runs once per seed (``seed=`` also draws the held-out set, so each
seed's rows are compared on the same questions); each seed gives its own throughput ratio (its rows
ran back to back, so a slow spell of the machine weighs on one seed's ratio, not on all), the
reported ratio is their mean and ``ratio_spread`` lists them with their range and standard
deviation; the held-out gap is the mean of the per-seed gaps, and each seed's results are listed.

Last stdout line: {"benchmark": "async_vs_sync", "ratios": {"grpo_async_vs_sync": sync training
time / eta=1 training time (same samples: the throughput ratio; the mean of the per-seed ratios),
"grpo_async2_vs_sync": eta=2's, "grpo_overlap_ceiling": 2 x sync / sync1 (the bound above),
"grpo_async_partial_vs_sync" / "grpo_async2_partial_vs_sync": with
partial rollouts, "ppo_async_vs_sync", "ppo_async2_vs_sync"; null where a row failed},
"ratio_spread": {ratio key: {"per_seed", "mean", "min", "max", "sd" (null with one seed)}},
"metric_gap_points": {job: {row: sync final - row final, in points (mean over seeds)}},
"metric_gap_se_points": {job: {row: its standard error over seeds (null with one seed)}}, "targets": ...,
"results": {job: {row: ...}} (with several seeds: {job: {row: {"seed=N": ...}}}), "failures": [...]}.
A row that fails is listed in "failures" (its entry holds "failed") and the script exits 1.
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
from dataclasses import dataclass

from _bench_common import add_record_argument, conclude, concluded


@dataclass(frozen=True)
class Row:
    max_staleness: int | None  # None: the synchronous loop
    partial_rollout: bool = False  # language models only: weight updates interrupt generations in flight
    # The synchronous loop with one thread each for the actor and the rollout (the asynchronous rows'
    # threads): its time is the step's whole work on one core, whose half bounds any overlap on two.
    one_thread_each: bool = False

    def ratio_key(self, job: str) -> str:
        if self.one_thread_each:
            return f"{job}_overlap_ceiling"
        eta = "" if self.max_staleness == 1 else str(self.max_staleness)
        return f"{job}_async{eta}{'_partial' if self.partial_rollout else ''}_vs_sync"


ROWS = {"sync": Row(None), "eta1": Row(1), "eta2": Row(2), "eta1_partial": Row(1, partial_rollout=True),
        "eta2_partial": Row(2, partial_rollout=True), "sync1": Row(None, one_thread_each=True)}
DEFAULT_ROWS = ("sync", "eta1", "eta2", "eta1_partial", "eta2_partial")


@dataclass(frozen=True)
class Job:
    config: str
    metric: str  # the held-out metric
    time_key: str  # seconds of one iteration, evaluation excluded
    correction: tuple[str, ...]
    threads: tuple[str, str] | None  # the actor's and the rollout's thread keys, set in asynchronous rows
    eval_every: int
    target: float | None


JOBS = {
    "grpo": Job("grpo_arithmetic", "eval/greedy_accuracy", "time/step_s",
                ("algorithm.objective.is_cap=2.0", "algorithm.objective.is_cap_mode=mask"),
                ("num_threads", "rollout.num_threads"), 5, 1.5),
    "ppo": Job("ppo_metaworld_reach", "eval/success_rate", "time/iteration_s", ("algorithm.is_cap=2.0",),
               None, 10, 1.2),
}


def overrides(job: Job, row: str, iterations: int | None, out: str, async_threads: tuple[int, int],
              seed: int | None = None) -> list[str]:
    args = [f"eval.every={job.eval_every}", f"output_dir={out}", "resume=false", "loggers=[]",
            "save_every=100000", "cluster.log_to_driver=false", "eval.video_episodes=0"]
    if seed is not None:
        args.append(f"seed={seed}")
    if iterations:
        args.append(f"iterations={iterations}")
    if job.config == "grpo_arithmetic":
        args.remove("eval.video_episodes=0")  # no video in the reasoning runner
    eta = ROWS[row].max_staleness
    if eta is not None:
        args += [f"algorithm.asynchronous.max_staleness={eta}", *job.correction]
        if job.threads:
            args += [f"{key}={n}" for key, n in zip(job.threads, async_threads)]
    if ROWS[row].one_thread_each and job.threads:
        args += [f"{key}={n}" for key, n in zip(job.threads, async_threads)]
    if ROWS[row].partial_rollout:
        args.append("algorithm.asynchronous.partial_rollout=true")
    return args


#: Asynchronous runners: the wait for the batches in flight before an evaluation (training time).
DRAIN_KEY = "time/eval_drain_s"


def summarise(job: Job, out: str) -> dict:
    rows = [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl"))]
    steps = [r for r in rows if job.time_key in r]
    train_s, drain_s, clock, curve = 0.0, 0.0, {}, []
    for r in rows:  # training time (iteration times and the waits before evaluations) at each evaluation
        drain_s += r.get(DRAIN_KEY, 0.0)
        train_s += r.get(job.time_key, 0.0) + r.get(DRAIN_KEY, 0.0)
        if job.time_key in r:
            clock[r["step"]] = train_s
    for r in rows:
        if job.metric in r:
            curve.append({"step": r["step"], "train_s": round(clock.get(r["step"], 0.0), 1), "metric": r[job.metric]})
    partial = [r["async/interrupted_fraction"] for r in steps if "async/interrupted_fraction" in r]
    return {
        "iterations": len(steps),
        "train_s": round(train_s, 1),
        "eval_drain_s": round(drain_s, 1),
        "median_iteration_s": round(statistics.median(r[job.time_key] for r in steps[1:] or steps), 2),
        "staleness_mean": statistics.mean(r.get("async/staleness_mean", 0.0) for r in steps),
        **({"interrupted_fraction_mean": statistics.mean(partial),
            "token_staleness_mean": statistics.mean(r["async/token_staleness_mean"] for r in steps)}
           if partial else {}),
        "eval": curve,
        "final_metric": curve[-1]["metric"] if curve else None,
    }


def seed_ratios(sync_runs: dict, runs: dict, scale: float = 1.0) -> dict | None:
    """Per seed, ``scale`` x the synchronous training time over the row's (a seed's rows ran back to
    back), and their mean, range and standard deviation (None with one seed); None if a seed lacks
    either time (failed or skipped). ``scale`` 2 turns the one-thread-each row's time into the overlap
    ceiling (see :data:`ROWS`' ``sync1``)."""
    seeds = list(runs)
    times = [(sync_runs.get(s, {}).get("train_s"), runs[s].get("train_s")) for s in seeds]
    if not seeds or not all(sync and row for sync, row in times):
        return None
    ratios = [scale * sync / row for sync, row in times]
    return {"per_seed": {"default" if s is None else str(s): round(r, 3) for s, r in zip(seeds, ratios)},
            "mean": round(statistics.mean(ratios), 3), "min": round(min(ratios), 3), "max": round(max(ratios), 3),
            "sd": round(statistics.stdev(ratios), 3) if len(ratios) > 1 else None}


def paired_gap(pairs: list[tuple[float, float]]) -> dict:
    """The synchronous final metric minus a row's, in points: the mean over seeds of the paired
    differences and its standard error (None with one seed)."""
    diffs = [100 * (sync - row) for sync, row in pairs]
    se = statistics.stdev(diffs) / len(diffs) ** 0.5 if len(diffs) > 1 else None
    return {"mean": round(statistics.mean(diffs), 1), "se": None if se is None else round(se, 1), "seeds": len(diffs)}


def time_to(curve: list[dict], value: float) -> float | None:
    """Training seconds until the held-out metric first reaches ``value``."""
    return next((point["train_s"] for point in curve if point["metric"] >= value - 1e-9), None)


def run_rows(name: str, wanted: list[str], seeds: list, args, async_threads: tuple[int, int],
             failures: list[str]) -> dict:
    """Every row of job ``name`` once per seed, one after the other: {row: {seed: result}}; a row
    that fails holds ``failed`` and is added to ``failures``."""
    job, per_seed = JOBS[name], {}
    for seed in seeds:
        for row in wanted:
            if (ROWS[row].partial_rollout or ROWS[row].one_thread_each) and not job.threads:
                skipped = ("partial rollouts interrupt language-model generation only" if ROWS[row].partial_rollout
                           else "the job's config already gives the actor and the rollout one thread each")
                per_seed.setdefault(row, {})[seed] = {"skipped": skipped}
                continue
            out = tempfile.mkdtemp(prefix=f"bench-async-{name}-{row}-")
            command = [sys.executable, "-m", "infinirl.cli", "train", job.config,
                       *overrides(job, row, args.iterations, out, async_threads, seed), *args.extra]
            start = time.perf_counter()
            proc = subprocess.run(command, capture_output=True, text=True)
            failed = {"failed": f"exit {proc.returncode}: {proc.stderr[-1500:]}"}
            res = failed if proc.returncode else summarise(job, out)
            res["wall_s"] = round(time.perf_counter() - start, 1)
            res["command"] = "infinirl " + " ".join(command[3:])
            per_seed.setdefault(row, {})[seed] = res
            if proc.returncode:
                failures.append(f"{name} {row} seed={seed}: exit {proc.returncode} (stderr in its result)")
            print(f"[{name} {row} seed={seed}] {json.dumps(res)[:600]}", file=sys.stderr, flush=True)
    return per_seed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", default=",".join(JOBS), help=f"comma-separated, from {', '.join(JOBS)}")
    parser.add_argument("--iterations", type=int, default=None, help="default: each config's own")
    parser.add_argument("--rows", default=",".join(DEFAULT_ROWS),
                        help=f"comma-separated, from {', '.join(ROWS)} (default: {', '.join(DEFAULT_ROWS)})")
    parser.add_argument("--async-threads", default="1,1",
                        help="grpo: torch threads of the actor and of the rollout in the asynchronous rows (they run "
                             "at the same time; the synchronous row keeps the job's 2 and 2, used one after the other)")
    parser.add_argument("--seeds", default="",
                        help="comma-separated seeds: each row runs once per seed (default: the config's seed)")
    parser.add_argument("--set", dest="extra", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for every row (repeatable), e.g. an lr schedule both rows share")
    add_record_argument(parser)
    args = parser.parse_args()
    jobs = [j.strip() for j in args.jobs.split(",") if j.strip()]
    wanted = [r.strip() for r in args.rows.split(",") if r.strip()]
    for option, chosen, known in (("--jobs", jobs, JOBS), ("--rows", wanted, ROWS)):
        unknown = sorted(set(chosen) - set(known))
        if unknown:
            parser.error(f"{option}: unknown {unknown}; choose from {', '.join(known)}")
    async_threads = tuple(int(x) for x in args.async_threads.split(","))
    seeds = [int(x) for x in args.seeds.split(",") if x.strip()] or [None]
    results: dict = {}
    ratios, spreads, gaps, gap_se, to_final, failures = {}, {}, {}, {}, {}, []
    for name in jobs:
        per_seed = run_rows(name, wanted, seeds, args, async_threads, failures)
        results[name] = {row: runs[None] if seeds == [None] else {f"seed={s}": r for s, r in runs.items()}
                         for row, runs in per_seed.items()}
        sync_runs = per_seed.get("sync", {})
        for row, runs in per_seed.items():
            if row != "sync" and sync_runs and not all("skipped" in r for r in runs.values()):
                # same samples: the throughput ratio, per seed; null where a row failed
                spread = seed_ratios(sync_runs, runs, scale=2.0 if ROWS[row].one_thread_each else 1.0)
                ratios[ROWS[row].ratio_key(name)] = spread["mean"] if spread else None
                if spread:
                    spreads[ROWS[row].ratio_key(name)] = spread
            paired = [(sync_runs[s]["final_metric"], runs[s]["final_metric"]) for s in seeds
                      if sync_runs.get(s, {}).get("final_metric") is not None
                      and runs.get(s, {}).get("final_metric") is not None]
            if paired:
                summary = paired_gap(paired)
                gaps.setdefault(name, {})[row] = summary["mean"]
                gap_se.setdefault(name, {})[row] = summary["se"]
                if seeds == [None]:
                    to_final.setdefault(name, {})[row] = time_to(runs[None]["eval"], sync_runs[None]["final_metric"])
    final = {"benchmark": "async_vs_sync", "ratios": ratios, "ratio_spread": spreads,
             "targets": {f"{name}_async_vs_sync": JOBS[name].target for name in jobs},
             "metric_gap_points": gaps, "metric_gap_se_points": gap_se, "train_s_to_sync_final_metric": to_final,
             "device": f"{platform.processor() or platform.machine()} ({os.cpu_count()} cpus)",
             "iterations": args.iterations, "seeds": [s for s in seeds if s is not None],
             "async_threads": list(async_threads), "results": results}
    return conclude(final, failures, record=(args.record, "Asynchronous vs synchronous training"))


if __name__ == "__main__":
    sys.exit(concluded("async_vs_sync", main))
