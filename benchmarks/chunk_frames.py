"""Benchmark: env steps per second of chunked pixel envs, inner frames skipped vs all rendered.

A policy that emits chunks of K actions reads one observation per chunk, so the frames of the
K - 1 inner steps are drawn for nobody. ``ActionChunkEnv`` tells the sub-envs so (``observe=False``)
and MetaWorld repeats its last frame there instead of rendering; the frames that are read (a
chunk's last step, an episode's last step, a reset) are the same bytes either way
(tests/unit/envs/test_metaworld_env.py). This benchmark steps the same envs, seeds and random
action chunks both ways:

* ``skip``: ``ActionChunkEnv(VectorEnv(...), K)`` (the default);
* ``full``: ``ActionChunkEnv(VectorEnv(...), K, skip_inner_frames=False)`` (a frame every step).

The two rows are built once and take turns, ``--rounds`` rounds of ``--chunks`` chunks each, so a
slow spell of a shared machine lands on both; the rate of a row is its total env steps over its
total time. The env comes from a demo config (``--config``, default the VLA demo
``ppo_vla_metaworld``: its env, options, env count and chunk; ``ppo_pi0_libero`` steps LIBERO),
so the benchmark measures the loop that demo runs; flags override single fields.

    python benchmarks/chunk_frames.py
    python benchmarks/chunk_frames.py --config ppo_pi0_libero --num-envs 2 --chunks 20 --record docs/results.md

Last stdout line: {"benchmark": "chunk_frames", "ratios": {"chunk_frames_skip_vs_full": skip env
steps/s over full env steps/s}, "device": ..., "results": {row: {...}}, "config": {...}}.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import add_record_argument, conclude, concluded, device_description  # noqa: E402

ROWS = ("skip", "full")
DEMO = "ppo_vla_metaworld"


def demo_env(config: str = DEMO) -> dict:
    """The env a demo config trains in: {env (registry name), kwargs, num_envs, chunk}."""
    from infinirl.config import compose

    raw = compose(config)
    chunk = int(raw["policy"].get("chunk") or 1)
    kwargs = dict(raw["env"].get("kwargs") or {})
    return {"env": raw["env"]["name"], "kwargs": kwargs, "num_envs": int(raw["env"]["num_envs"]), "chunk": chunk}


def summarise(seconds: list[float], env_steps: list[int]) -> dict:
    """Per-round times and env-step counts of one row -> its totals and rate."""
    total_s, total_steps = sum(seconds), sum(env_steps)
    return {
        "env_steps": total_steps,
        "seconds": round(total_s, 3),
        "env_steps_per_s": round(total_steps / total_s, 1) if total_s > 0 else 0.0,
        "round_s": [round(s, 3) for s in seconds],
    }


def _build(args: argparse.Namespace, skip: bool):
    from infinirl.envs import ActionChunkEnv, make_env

    kwargs = dict(args.kwargs)
    if args.image_size is not None:
        kwargs["image_size"] = args.image_size
    vector = make_env(args.env, args.num_envs, num_workers=args.num_workers, seed=0, **kwargs)
    return ActionChunkEnv(vector, args.chunk, skip_inner_frames=skip)


def _run_round(env, chunks) -> tuple[float, int]:
    """Step every chunk; seconds taken and env steps executed (a chunk can stop at an episode end)."""
    env.reset(seeds=0)
    steps = 0
    start = time.perf_counter()
    for actions in chunks:
        steps += int(env.step(actions).info["step_mask"].sum())
    return time.perf_counter() - start, steps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=DEMO, help="the demo config whose env is stepped")
    parser.add_argument("--num-envs", type=int, help="default: the config's")
    parser.add_argument("--num-workers", type=int, help="env worker processes (default: one per core)")
    parser.add_argument("--image-size", type=int, help="default: the config's")
    parser.add_argument("--chunk", type=int, help="actions per chunk, K (default: the config's policy.chunk)")
    parser.add_argument("--chunks", type=int, default=50, help="chunks per round (50 x 4 = one 200-step episode)")
    parser.add_argument("--rounds", type=int, default=3)
    add_record_argument(parser)
    args = parser.parse_args()
    for key, value in demo_env(args.config).items():
        if getattr(args, key, None) is None:
            setattr(args, key, value)
    if args.chunk < 2:
        raise SystemExit(f"chunks of {args.chunk} action (--config {args.config}'s policy.chunk, or --chunk) have no "
                         "inner step to skip: give --chunk K with K >= 2")

    import numpy as np

    envs = {row: _build(args, skip=row == "skip") for row in ROWS}
    spec = envs["skip"].observation_spec
    frames = [key for key, field in spec.items() if field.dtype == "uint8" and len(field.shape) == 3]
    if not frames:
        for env in envs.values():
            env.close()
        raise SystemExit(f"--config {args.config}: its env {args.env} gives no camera frames (observation keys "
                         f"{sorted(spec)}); use a config whose env renders, e.g. env.kwargs "
                         "obs_mode: state+rgb")
    space = envs["skip"].env.action_space
    rng = np.random.default_rng(0)
    chunks = [rng.uniform(space.low, space.high, (args.num_envs, args.chunk, *space.shape)).astype(np.float32)
              for _ in range(args.chunks)]
    times: dict[str, list[float]] = {row: [] for row in ROWS}
    steps: dict[str, list[int]] = {row: [] for row in ROWS}
    try:
        for row in ROWS:  # warm-up: first renders create the GL contexts
            _run_round(envs[row], chunks[:2])
        for r in range(args.rounds):
            order = ROWS if r % 2 == 0 else ROWS[::-1]
            for row in order:
                seconds, n = _run_round(envs[row], chunks)
                times[row].append(seconds)
                steps[row].append(n)
                print(f"round {r} {row}: {n} env steps in {seconds:.2f} s ({n / seconds:.1f}/s)", flush=True)
    finally:
        for env in envs.values():
            env.close()
    results = {row: summarise(times[row], steps[row]) for row in ROWS}
    ratio = results["skip"]["env_steps_per_s"] / results["full"]["env_steps_per_s"]
    final = {
        "benchmark": "chunk_frames",
        "ratios": {"chunk_frames_skip_vs_full": round(ratio, 3)},
        "device": device_description(),
        "results": results,
        "config": {k: v for k, v in vars(args).items() if k != "record"},
    }
    return conclude(final, record=(args.record, "Inner frames of action chunks: skipped vs rendered"))


if __name__ == "__main__":
    sys.exit(concluded("chunk_frames", main))
