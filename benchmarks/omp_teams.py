"""Benchmark: the pixels PPO update on the compute thread, alone in OpenMP vs after one parallel op
on a second thread, and alone vs beside an idle Ray instance. Why it exists: a Worker rank computes
on a thread of its own (the process's main thread runs Ray's event loop), and its constructor runs
on that thread too (a constructor on the main thread would start a second OpenMP team); and an
actor rank's update always has Ray beside it, which row
(c) of ``embodied_pipeline.py`` (one process, no Ray) does not.

torch's intra-op threads are libgomp's. Every thread that starts a parallel region gets its own
team of helper threads, and once the teams hold more threads than the process has cores, libgomp
cuts every waiting thread's spin to ~100 turns (0 under ``OMP_WAIT_POLICY=PASSIVE``, which our
workers run with) before it sleeps in the kernel. An update is thousands of short parallel regions,
so the helper thread is put to sleep and woken between nearly every pair of them.

Two processes, each with the actor's OpenMP settings (``OMP_WAIT_POLICY=PASSIVE`` from
``runtime.cluster``, ``GOMP_SPINCOUNT`` from ``utils.threads.spin_wait_env``) and every core:

  one_team:  build the CNN policy and run ``ppo_update`` on one worker thread (how a Worker rank
             computes now: constructor and methods on its compute thread);
  two_teams: the same after one parallel torch op on the main thread (what a constructor on the
             main thread would cause).
  beside_ray: one_team while a local Ray instance of ours idles beside it, with three idle
             components (a pipelined row's env, rollout and actor, minus their work). Every Ray
             worker's main thread wakes every 10 ms, and Ray's daemons poll: hundreds of wake-ups a
             second, each of which may preempt one of the update's two OpenMP threads while
             the other waits for it at the next barrier (the involuntary context switches).

Each runs the update (1,600 samples of 64x64 RGB + proprio, 10 epochs x 32 mini-batches, compiled
like the benchmark rows) ``--updates`` times after a warm-up; reports the median seconds and the
voluntary context switches per update (the sleeps) and the involuntary ones (preemptions).
``--repeats`` processes per variant run in turn, the order reversed every repeat; each ratio is the
median over repeats of (variant's update) / (one_team's update).

Usage:
    python benchmarks/omp_teams.py               # minutes
    python benchmarks/omp_teams.py --updates 5

The last stdout line is one JSON object: {"benchmark": "omp_teams", "ratios":
{"one_team_vs_two_teams": ..., "alone_vs_beside_ray": ...}, "results": {...}, "failures": [...]} (> 1:
one team, alone, is faster). A variant's process that fails ends the run: its entry holds "failed",
the ratios are null, and the script exits 1.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
VARIANTS = ("one_team", "two_teams", "beside_ray")
#: ratio key -> the variant compared with one_team
RATIOS = {"one_team_vs_two_teams": "two_teams", "alone_vs_beside_ray": "beside_ray"}
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import add_record_argument, conclude, concluded, failures_of, side_failed  # noqa: E402


def _child(variant: str, updates: int) -> dict:
    import resource
    from concurrent.futures import ThreadPoolExecutor

    import torch

    torch.set_num_threads(len(os.sched_getaffinity(0)))
    if variant == "two_teams":
        torch.randn(4_000_000).exp_()  # one parallel region on the main thread
    compute = ThreadPoolExecutor(max_workers=1)
    state = compute.submit(_build).result()

    def timed_update(iteration: int) -> tuple[float, int, int]:
        import time

        from infinirl.components.embodied_actor import ppo_update

        model, optimizer, batch, ppo = state
        before, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        ppo_update(model, optimizer, batch, iteration, ppo)
        seconds, after = time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF)
        return seconds, after.ru_nvcsw - before.ru_nvcsw, after.ru_nivcsw - before.ru_nivcsw

    compute.submit(timed_update, 0).result()  # compile
    runs = [compute.submit(timed_update, i + 1).result() for i in range(updates)]
    return {"update_s": round(statistics.median(r[0] for r in runs), 3),
            "sleeps_per_update": int(statistics.median(r[1] for r in runs)),
            "preemptions_per_update": int(statistics.median(r[2] for r in runs)),
            "all_update_s": [round(r[0], 3) for r in runs]}


def _build():
    import torch

    from infinirl.components.embodied_actor import PPOSpec
    from infinirl.components.embodied_rollout import PolicySpec
    from infinirl.components.env_worker import probe_env_specs
    from infinirl.config import compose

    raw = compose("ppo_metaworld_reach")
    alg = raw["algorithm"]
    spec, space = probe_env_specs(raw["env"]["name"], {"obs_mode": "state+rgb", "image_size": 64})
    torch.manual_seed(0)
    model = PolicySpec(name="cnn_gaussian", options={}).build(spec, space)
    size = 1600  # 8 envs x 200 steps, one iteration of the pipeline benchmark
    gen = torch.Generator().manual_seed(1)
    obs = {key: (torch.randint(0, 255, (size, *s.shape), dtype=torch.uint8, generator=gen) if s.dtype == "uint8"
                 else torch.randn(size, *s.shape, generator=gen)) for key, s in spec.items() if s.dtype != "str"}
    with torch.no_grad():
        step = model.act(obs)
    batch = {"obs": obs, "actions": step.actions, "logprobs": step.logprobs, "values": step.values,
             "step_mask": torch.ones(size, 1, dtype=torch.bool),
             "advantages": torch.randn(size, generator=gen), "returns": torch.randn(size, generator=gen)}
    ppo = PPOSpec(lr=raw["actor"]["lr"], epochs=alg["epochs"], mini_batches=alg["mini_batches"], clip=alg["clip"],
                  entropy_coef=alg["entropy_coef"], max_grad_norm=alg["max_grad_norm"], total_iterations=100,
                  compile=True)
    optimizer = torch.optim.Adam(model.parameters(), lr=ppo.lr, eps=ppo.adam_eps, fused=True)
    return model, optimizer, batch, ppo


def _idle_ray() -> None:
    """Start a local Ray instance as the runners do (``Cluster``), launch three idle components,
    print ``up`` and idle until stdin closes."""
    from infinirl.runtime import Cluster, Worker, WorkerGroup

    class IdleComponent(Worker):
        """A component with nothing to do: what is left of a rank between its calls."""

    with Cluster():
        groups = [WorkerGroup.launch(IdleComponent, num_ranks=1, component=name)
                  for name in ("env", "rollout", "actor")]
        print("up", flush=True)
        sys.stdin.read()
        for group in groups:
            group.shutdown()


def _beside_idle_ray(command: list[str], env: dict) -> subprocess.CompletedProcess:
    """Run ``command`` while :func:`_idle_ray` idles in another process (its stderr goes to a
    temporary file, shown if the instance fails to start)."""
    import tempfile

    log = tempfile.TemporaryFile(mode="w+")
    ray_proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--idle-ray"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=log, text=True, env=env)
    try:
        for line in ray_proc.stdout:
            if line.strip() == "up":
                break
        else:
            code = ray_proc.wait()
            log.seek(0)
            raise RuntimeError(f"the idle Ray instance for beside_ray did not start (exit code {code}):\n"
                               f"{log.read()[-4000:]}")
        return subprocess.run(command, capture_output=True, text=True, env=env)
    finally:
        log.close()
        ray_proc.stdin.close()
        try:
            ray_proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            ray_proc.kill()
            ray_proc.wait()


def _child_env() -> dict:
    from infinirl.runtime.cluster import WORKER_ENV_DEFAULTS
    from infinirl.utils.threads import spin_wait_env

    env = {**os.environ, **WORKER_ENV_DEFAULTS, **spin_wait_env(0)}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO_ROOT, env.get("PYTHONPATH")) if p)
    return env


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, default=3, help="measured updates per variant (after one warm-up)")
    parser.add_argument("--repeats", type=int, default=2, help="processes per variant, run alternately")
    parser.add_argument("--child", choices=VARIANTS, help=argparse.SUPPRESS)
    parser.add_argument("--idle-ray", action="store_true", help=argparse.SUPPRESS)
    add_record_argument(parser)
    args = parser.parse_args()
    if args.idle_ray:
        _idle_ray()
        return 0
    if args.updates < 1 or args.repeats < 1:
        parser.error(f"--updates and --repeats must be >= 1, got {args.updates} and {args.repeats}")
    if args.child:
        print(json.dumps(_child(args.child, args.updates)))
        return 0
    runs = {variant: [] for variant in VARIANTS}
    for repeat in range(args.repeats):  # the order reversed every repeat, so a drifting machine lands on all
        for variant in VARIANTS if repeat % 2 == 0 else VARIANTS[::-1]:
            command = [sys.executable, os.path.abspath(__file__), "--child", variant, "--updates", str(args.updates)]
            env = _child_env()
            proc = (_beside_idle_ray(command, env) if variant == "beside_ray"
                    else subprocess.run(command, capture_output=True, text=True, env=env))
            if proc.returncode:  # the other variants would be compared with nothing: stop here
                failed = {variant: side_failed(f"exit {proc.returncode}:\n{proc.stderr[-4000:]}")}
                return conclude({"benchmark": "omp_teams", "ratios": {key: None for key in RATIOS},
                                 "results": {**{v: {"runs": rs} for v, rs in runs.items()}, **failed}},
                                failures_of(failed))
            run = json.loads(proc.stdout.strip().splitlines()[-1])
            runs[variant].append(run)
            print(f"{variant:10s} update {run['update_s']:.2f}s  {run['sleeps_per_update']} sleeps, "
                  f"{run['preemptions_per_update']} preemptions per update", file=sys.stderr)
    per_repeat = {key: [round(other["update_s"] / one["update_s"], 3)
                        for one, other in zip(runs["one_team"], runs[variant])]
                  for key, variant in RATIOS.items()}
    ratios = {key: round(statistics.median(values), 3) for key, values in per_repeat.items()}
    for key, value in ratios.items():
        print(f"{key}: {value} (per repeat {per_repeat[key]})", file=sys.stderr)
    results = {variant: {"update_s": round(statistics.median(r["update_s"] for r in rs), 3),
                         "sleeps_per_update": int(statistics.median(r["sleeps_per_update"] for r in rs)),
                         "preemptions_per_update": int(statistics.median(r["preemptions_per_update"] for r in rs)),
                         "runs": rs} for variant, rs in runs.items()}
    final = {"benchmark": "omp_teams", "ratios": ratios, "per_repeat": per_repeat, "results": results,
             "device": f"{os.uname().machine}, {len(os.sched_getaffinity(0))} CPUs"}
    return conclude(final, record=(args.record, "omp_teams"))


if __name__ == "__main__":
    sys.exit(concluded("omp_teams", main))
