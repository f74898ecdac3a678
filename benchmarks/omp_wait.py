"""Benchmark: the demo VLA acting on a worker's compute thread, its OpenMP threads waiting passively
vs spinning ~3 ms before they sleep.

Every worker process starts with ``OMP_WAIT_POLICY=PASSIVE`` (``runtime.cluster``): a helper thread
that finishes a parallel region sleeps in the kernel at once, so an idle process gives its cores
back. A rank computing with several threads (``rollout.num_threads: 2`` in the VLA demos) runs the
VLA's prefix and ten denoising steps as hundreds of short parallel regions a decision, and waking
the sleeping helper for each costs more than many of the kernels. ``utils.threads.spin_wait_env``
gives such a rank ``GOMP_SPINCOUNT`` (libgomp's own default spin) from its process's start.

Two rows, each a fresh process with the workers' OpenMP settings, the config's torch threads and its
policy built from the SFT checkpoint, acting (sampling, as in collection) on a compute thread of its
own as a Worker rank does, on the same real MetaWorld observations of the config's envs:

  passive: ``OMP_WAIT_POLICY=PASSIVE`` alone (how every rollout rank ran before);
  spin:    the same plus ``spin_wait_env(threads)`` (how a rank with several threads runs now).

``--repeats`` processes per row run in turn, the order reversed every repeat; each reports the
median seconds of ``--calls`` calls after a warm-up. The ratio is the median over repeats of
passive's seconds over spin's (> 1: spinning is faster).

    python benchmarks/omp_wait.py                 # runs/sft_vla_metaworld/policy, 12 envs, 2 threads
    python benchmarks/omp_wait.py --repeats 3 --record docs/results.md

Last stdout line: {"benchmark": "omp_wait", "ratios": {"vla_act_spin_vs_passive": ...},
"device": ..., "results": {...}, "config": {...}, "failures": [...]}. A row's process that fails ends
the run: its entry holds "failed", the ratio is null, and the script exits 1.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import (  # noqa: E402
    add_record_argument,
    conclude,
    concluded,
    device_description,
    failures_of,
    side_failed,
)
from vla_dtype import DEMO, demo_setup  # noqa: E402

ROWS = ("passive", "spin")


def child(args: argparse.Namespace) -> None:
    """One row: build, observe, act on a compute thread; print the median seconds as JSON."""
    from concurrent.futures import ThreadPoolExecutor

    def measure() -> dict:
        import time

        import torch

        from infinirl.components.embodied_policy import policy_kwargs
        from infinirl.components.embodied_rollout import array_obs
        from infinirl.envs import make_env
        from infinirl.models.policies.base import build_policy, prepare_obs

        setup = demo_setup(args.config)
        torch.set_num_threads(args.threads)
        env = make_env(setup["env"], args.num_envs, num_workers=1, seed=0, **setup["env_kwargs"])
        try:
            obs = prepare_obs(array_obs(env.reset(seeds=list(range(args.num_envs)))), "cpu")
            options = {**setup["options"], "checkpoint": args.checkpoint}
            torch.manual_seed(0)
            policy = build_policy(setup["policy"], **policy_kwargs(setup["policy"], options, env.observation_spec,
                                                                   env.action_space, setup["chunk"])).eval()
        finally:
            env.close()
        seconds = []
        with torch.no_grad():
            for call in range(args.warmup + args.calls):
                start = time.perf_counter()
                policy.act(obs)
                if call >= args.warmup:
                    seconds.append(time.perf_counter() - start)
        return {"median_s": statistics.median(seconds), "threads": torch.get_num_threads()}

    # A Worker rank's constructor and methods run on one compute thread, not the main one.
    with ThreadPoolExecutor(max_workers=1) as compute:
        print(json.dumps(compute.submit(measure).result()))


def row_env(row: str, threads: int) -> dict:
    from infinirl.runtime.cluster import WORKER_ENV_DEFAULTS
    from infinirl.utils.threads import spin_wait_env

    env = {**os.environ, **WORKER_ENV_DEFAULTS}
    env.pop("GOMP_SPINCOUNT", None)
    if row == "spin":
        env.update(spin_wait_env(threads))
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO_ROOT, env.get("PYTHONPATH")) if p)
    return env


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=DEMO, help="the demo config whose env and policy act")
    parser.add_argument("--checkpoint", help="the VLA folder (default: the config's policy.kwargs.checkpoint)")
    parser.add_argument("--num-envs", type=int, help="default: the config's")
    parser.add_argument("--threads", type=int, help="torch threads (default: the config's rollout.num_threads)")
    parser.add_argument("--calls", type=int, default=10, help="timed calls per process")
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls per process first")
    parser.add_argument("--repeats", type=int, default=2, help="processes per row, taking turns")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    add_record_argument(parser)
    args = parser.parse_args()
    setup = demo_setup(args.config)
    args.checkpoint = args.checkpoint or setup["options"].get("checkpoint")
    args.num_envs = args.num_envs or setup["num_envs"]
    args.threads = args.threads or setup["threads"] or os.cpu_count() or 1
    if args.child:
        child(args)
        return 0
    if not args.checkpoint or not os.path.isdir(args.checkpoint):
        raise SystemExit(f"--checkpoint {args.checkpoint!r} is not a VLA folder: run `infinirl train "
                         "sft_vla_metaworld` first (it writes runs/sft_vla_metaworld/policy) or pass --checkpoint DIR")
    if args.threads == 1:
        raise SystemExit("--threads 1: one thread has no helper threads to wait; the rows would be the same")
    command = [sys.executable, os.path.abspath(__file__), "--child", "--config", args.config, "--checkpoint",
               args.checkpoint, "--num-envs", str(args.num_envs), "--threads", str(args.threads),
               "--calls", str(args.calls), "--warmup", str(args.warmup)]
    seconds: dict[str, list[float]] = {row: [] for row in ROWS}
    config = {"config": args.config, "checkpoint": args.checkpoint, "num_envs": args.num_envs,
              "threads": args.threads, "calls": args.calls, "repeats": args.repeats}
    for repeat in range(args.repeats):
        for row in (ROWS if repeat % 2 == 0 else ROWS[::-1]):
            done = subprocess.run(command, env=row_env(row, args.threads), capture_output=True, text=True)
            if done.returncode != 0:  # the other row would be compared with nothing: stop here
                results = {**{r: {"per_repeat_s": seconds[r]} for r in ROWS},
                           row: side_failed(f"exit {done.returncode}:\n{done.stderr[-3000:]}")}
                return conclude({"benchmark": "omp_wait", "ratios": {"vla_act_spin_vs_passive": None},
                                 "device": device_description(), "results": results, "config": config},
                                failures_of(results))
            measured = json.loads(done.stdout.strip().splitlines()[-1])
            seconds[row].append(measured["median_s"])
            print(f"repeat {repeat} {row:>7}: {measured['median_s']:.4f} s a call of {args.num_envs} envs", flush=True)
    ratio = statistics.median(p / s for p, s in zip(seconds["passive"], seconds["spin"], strict=True))
    results = {row: {"median_s": round(statistics.median(seconds[row]), 4),
                     "decisions_per_s": round(args.num_envs / statistics.median(seconds[row]), 2),
                     "per_repeat_s": [round(s, 4) for s in seconds[row]]} for row in ROWS}
    final = {"benchmark": "omp_wait", "ratios": {"vla_act_spin_vs_passive": round(ratio, 3)},
             "device": device_description(), "results": results, "config": config}
    return conclude(final, record=(args.record, "VLA acting with OpenMP threads spinning vs waiting passively"))


if __name__ == "__main__":
    sys.exit(concluded("omp_wait", main))
