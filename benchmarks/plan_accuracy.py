"""Benchmark: predicted against measured step times of placements, and the scheduler's choice against hand-written ones.

For each job (``--jobs``): the reasoning demo (`grpo_chain_sum`) and the embodied demo
(`ppo_metaworld_reach`), each with the shipped config's work per iteration:

1. the profile (`infinirl plan`'s: probe runs, cached per config and hardware, so a second run of
   this benchmark reuses it) and the ranked plan on this machine's cluster;
2. short runs (``--iterations``, the first is warm-up) under the hand-written placements (the
   README's and docs' examples), the scheduler's choice, and the next-ranked candidates until at
   least ``--placements`` distinct ones are measured;
3. per placement: predicted and measured seconds per iteration (median of the measured
   iterations of the runner's own ``time/iteration_s`` / ``time/step_s``) and their ratio.

    python benchmarks/plan_accuracy.py                          # both jobs
    python benchmarks/plan_accuracy.py --jobs embodied --iterations 3
    python benchmarks/plan_accuracy.py --set embodied:env.num_envs=8 --set reasoning:prompts_per_step=4   # less work

Last stdout line: {"benchmark": "plan_accuracy", "ratios": {"<job>/<placement>": predicted / measured},
"within_20pct": {job: fraction of placements with |ratio - 1| <= 0.2}, "chosen_no_slower": {job: the
chosen placement's measured time <= the best hand-written one's}, "chosen_s_over_best_hand_written_s":
{job: the chosen placement's measured seconds over the best hand-written one's (above 1: the chosen
one is slower; a time ratio, unlike the X_vs_Y speed ratios of the other benchmarks)}, "results":
{job: per placement ...}, "host": ..., "failures": [...]}: a placement whose run failed holds "error"
and is listed there, and the script then exits 1 (the others' numbers are still reported). On a
shared machine, timings move with the other load: read the ratios with the host line, and rerun
when in doubt.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

from _bench_common import conclude, concluded

from infinirl.cli import build_config
from infinirl.results import host_probe
from infinirl.scheduler.auto import plan
from infinirl.scheduler.cost import Allocation, Candidate, predict
from infinirl.scheduler.profile import measure_candidate, workload_of
from infinirl.scheduler.workloads import RUNNER_MODELS

JOBS = {"embodied": "ppo_metaworld_reach", "reasoning": "grpo_chain_sum"}

# The hand-written placements: (component -> (first slot, slot count)), depth.
HAND_WRITTEN = {
    "embodied": {
        "collocated (default)": ({"env": (0, 1), "rollout": (0, 1), "actor": (0, 1)}, 1),
        "pipelined hybrid": ({"env": (0, 1), "rollout": (1, 1), "actor": (0, 1)}, 2),
        "pipelined hybrid, actor on both": ({"env": (0, 1), "rollout": (1, 1), "actor": (0, 2)}, 2),
    },
    "reasoning": {
        "collocated (default)": ({"actor": (0, 1), "rollout": (0, 1), "reward": (0, 1)}, 1),
        "disaggregated": ({"actor": (0, 1), "rollout": (1, 1), "reward": (1, 1)}, 1),
    },
}


def _candidate(devices: dict, depth: int) -> Candidate:
    return Candidate(allocations={c: Allocation(first=f, count=n, ranks=n) for c, (f, n) in devices.items()},
                     depth=depth)


def _key(candidate: Candidate) -> str:
    spec = " ".join(f"{k}={v}" for k, v in candidate.placement().items())
    return f"{spec} depth={candidate.depth}"


def _placements(job: str, entries, wanted: int) -> dict[str, tuple[Candidate, str]]:
    """Hand-written ones, the chosen one, then the next-ranked ones: key -> (candidate, role)."""
    chosen: dict[str, tuple[Candidate, str]] = {}
    for label, (devices, depth) in HAND_WRITTEN[job].items():
        candidate = _candidate(devices, depth)
        chosen[_key(candidate)] = (candidate, f"hand-written: {label}")
    best = entries[0].candidate
    chosen[_key(best)] = (best, "chosen" + (" (also " + chosen[_key(best)][1] + ")" if _key(best) in chosen else ""))
    for entry in entries[1:]:
        if len(chosen) >= wanted:
            break
        chosen.setdefault(_key(entry.candidate), (entry.candidate, "ranked"))
    return chosen


def run_job(job: str, iterations: int, profile_iterations: int, wanted: int, overrides: list[str],
            rounds: int = 1) -> dict:
    cfg = build_config(JOBS[job], overrides)[1]
    model = RUNNER_MODELS.get(cfg.runner)
    started = time.perf_counter()
    profile, entries = plan(cfg, iterations=profile_iterations, rounds=rounds)
    workload = workload_of(cfg, profile)
    rows = {}
    for key, (candidate, role) in _placements(job, entries, wanted).items():
        prediction = predict(workload, candidate)
        predicted = prediction.step_s
        try:
            run = measure_candidate(cfg, model, candidate, iterations, label=job)
        except Exception as exc:  # one placement that fails must not lose the others' numbers
            rows[key] = {"role": role, "predicted_s": round(predicted, 3), "error": f"{type(exc).__name__}: {exc}"}
            continue
        measured = statistics.median(run.step_s)
        rows[key] = {"role": role, "predicted_s": round(predicted, 3), "measured_s": round(measured, 3),
                     "measured_iterations_s": [round(s, 3) for s in run.step_s],
                     "ratio": round(predicted / measured, 3),
                     "predicted_phases_s": {k: round(v, 3) for k, v in prediction.phases.items()}}
    components = tuple(cfg.components())
    measured_profile = {"overhead_s": profile.overhead_s, "hop_s": profile.hop_s,
                        "probes": {r.probe.name: [round(s, 3) for s in r.step_s] for r in profile.probes},
                        # what the fit saw: each probe's measured work (median over its iterations) and
                        # the prediction for the probe's own placement, which should match its step time
                        "probe_work_s": {r.probe.name: _median_work(r.iterations) for r in profile.probes},
                        "probe_predicted_s": {
                            r.probe.name: round(predict(workload, r.probe.candidate(components)).step_s, 3)
                            for r in profile.probes}}
    return {"config": JOBS[job], "overrides": overrides, "profile": measured_profile,
            "candidates": len(entries), "placements": rows, "wall_s": round(time.perf_counter() - started, 1)}


def _median_work(iterations: list[dict]) -> dict[str, float]:
    keys = sorted({k for it in iterations for k in it})
    return {k: round(statistics.median([it[k] for it in iterations if k in it]), 3) for k in keys}


def summarise(results: dict) -> dict:
    ratios, within, no_slower, versus = {}, {}, {}, {}
    for job, result in results.items():
        rows = {k: r for k, r in result["placements"].items() if "ratio" in r}
        for key, row in rows.items():
            ratios[f"{job}/{key}"] = row["ratio"]
        within[job] = round(sum(abs(r["ratio"] - 1) <= 0.2 for r in rows.values()) / max(len(rows), 1), 3)
        chosen = [r for r in rows.values() if r["role"].startswith("chosen")]
        hand = [r["measured_s"] for r in rows.values() if "hand-written" in r["role"]]
        no_slower[job] = bool(chosen and hand and chosen[0]["measured_s"] <= min(hand))
        if chosen and hand:
            versus[job] = round(chosen[0]["measured_s"] / min(hand), 3)  # seconds over seconds: above 1 is slower
    return {"ratios": ratios, "within_20pct": within, "chosen_no_slower": no_slower,
            "chosen_s_over_best_hand_written_s": versus}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", default="embodied,reasoning", help="comma-separated: embodied, reasoning")
    parser.add_argument("--iterations", type=int, default=4, help="iterations of each measured run (first: warm-up)")
    parser.add_argument("--profile-iterations", type=int, default=4, help="iterations of each probe run")
    parser.add_argument("--profile-rounds", type=int, default=1,
                        help="runs of every probe, interleaved (a drifting load then shifts all probes alike)")
    parser.add_argument("--placements", type=int, default=5, help="distinct placements measured per job (>= 4)")
    parser.add_argument("--set", action="append", default=[], metavar="JOB:KEY=VALUE",
                        help="a config override for one job, e.g. embodied:env.num_envs=8 (repeatable)")
    args = parser.parse_args()
    overrides: dict[str, list[str]] = {job: [] for job in JOBS}
    for item in args.set:
        job, _, override = item.partition(":")
        if job not in JOBS or "=" not in override:
            parser.error(f"--set {item!r}: write JOB:KEY=VALUE with JOB one of {', '.join(JOBS)}")
        overrides[job].append(override)
    jobs = [j.strip() for j in args.jobs.split(",") if j.strip()]
    unknown = [j for j in jobs if j not in JOBS]
    if unknown or args.iterations < 2 or args.placements < 1:
        parser.error(f"--jobs from {', '.join(JOBS)} (got {unknown or jobs}); --iterations >= 2; --placements >= 1")
    results = {job: run_job(job, args.iterations, args.profile_iterations, args.placements, overrides[job],
                            args.profile_rounds)
               for job in jobs}
    for job, result in results.items():
        print(f"\n{job} ({result['config']}): {result['candidates']} candidates")
        for key, row in result["placements"].items():
            shown = row.get("error") or f"predicted {row['predicted_s']:.3f} s, measured {row['measured_s']:.3f} s, " \
                                        f"ratio {row['ratio']:.2f}"
            print(f"  {key:<55} {row['role']:<40} {shown}")
    failures = [f"{job}/{key}: {row['error']}" for job, result in results.items()
                for key, row in result["placements"].items() if "error" in row]
    return conclude({"benchmark": "plan_accuracy", **summarise(results), "results": results, "host": host_probe()},
                    failures)


if __name__ == "__main__":
    sys.exit(concluded("plan_accuracy", main))
