"""Benchmark: decisions per second of the demo VLA acting in MetaWorld, bfloat16 against float32.

A frozen VLA (the residual and steered demos, `ppo_vla_metaworld_residual`) spends most of an RL
iteration acting: the VLM's prefix and the action expert's denoising steps for every decision of
every env. On CPUs with native bf16 matrix products (AVX512-BF16, AMX) that work may run in
bfloat16 (`policy.kwargs.dtype=bfloat16`). This benchmark builds the demo config's policy twice
from the same checkpoint, once per dtype, and times `act` on the same batches of real observations
(the config's env, camera and env count, one batch per reset seed), the two rows taking turns batch
by batch so a slow spell of a shared machine lands on both. Reported per row: the dtype its weights
hold (`dtype`), the median seconds per call and `decisions_per_s` = envs / median; and how far the
bf16 actions are from the float32 ones on the same observations (noise-free acting: the residual at
its mean, the VLA from noise 0). On a CPU-only host without native bf16 the policy loads bfloat16
as float32 (`engines/cpu_dtype.py`): the two rows would then be the same, so the script measures
nothing, says so, and exits 1 (`INFINIRL_CPU_BF16=1` keeps bfloat16 there).

    python benchmarks/vla_dtype.py                      # runs/sft_vla_metaworld/policy, 12 envs
    python benchmarks/vla_dtype.py --checkpoint /models/my_pi0_smollm2 --batches 20 --record docs/results.md

Last stdout line: {"benchmark": "vla_dtype", "ratios": {"vla_act_bf16_vs_fp32": bf16 decisions/s
over float32 decisions/s}, "device": ..., "results": {row: {...}}, "config": {...}, "failures": [...]}.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import (  # noqa: E402
    add_record_argument,
    conclude,
    concluded,
    device_description,
    failures_of,
)

ROWS = ("float32", "bfloat16")
DEMO = "ppo_vla_metaworld_residual"


def demo_setup(config: str) -> dict:
    """What a demo config acts with: env name, kwargs and count, policy name, chunk and options."""
    from infinirl.config import compose

    raw = compose(config)
    return {"env": raw["env"]["name"], "env_kwargs": dict(raw["env"].get("kwargs") or {}),
            "num_envs": int(raw["env"]["num_envs"]), "policy": raw["policy"]["name"],
            "chunk": int(raw["policy"].get("chunk") or 1), "options": dict(raw["policy"].get("kwargs") or {}),
            "threads": int((raw.get("rollout") or {}).get("num_threads") or 0)}


def summarise(seconds: list[float], num_envs: int) -> dict:
    median = statistics.median(seconds)
    return {"calls": len(seconds), "median_s": round(median, 4), "decisions_per_s": round(num_envs / median, 2),
            "call_s": [round(s, 4) for s in seconds]}


def weights_dtype(module) -> str:
    """The dtype that holds most of ``module``'s parameter elements (a VLA's few float32 heads beside
    its bfloat16 backbone do not decide it)."""
    counts: dict[str, int] = {}
    for parameter in module.parameters():
        name = str(parameter.dtype).removeprefix("torch.")
        counts[name] = counts.get(name, 0) + parameter.numel()
    return max(counts, key=counts.get) if counts else "none"


def dtype_failures(dtypes: dict[str, str]) -> dict[str, str]:
    """Per row whose weights are not in the dtype it is named after (the comparison would be void), why."""
    failed = {row: f"its weights are {dtypes[row]}" for row in ROWS if dtypes[row] != row}
    if "bfloat16" in failed:
        failed["bfloat16"] += (": this CPU has no native bf16, so the policy loads bfloat16 as float32 (set "
                               "INFINIRL_CPU_BF16=1 to keep bfloat16, or run on a CPU with AVX512-BF16/AMX)")
    return failed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=DEMO, help="the demo config whose env and policy act")
    parser.add_argument("--checkpoint", help="the VLA folder (default: the config's policy.kwargs.checkpoint)")
    parser.add_argument("--num-envs", type=int, help="default: the config's")
    parser.add_argument("--batches", type=int, default=10, help="timed calls per row (one reset seed each)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls per row first")
    parser.add_argument("--threads", type=int, help="torch threads (default: the config's rollout.num_threads)")
    add_record_argument(parser)
    args = parser.parse_args()
    setup = demo_setup(args.config)
    checkpoint = args.checkpoint or setup["options"].get("checkpoint")
    if not checkpoint or not os.path.isdir(checkpoint):
        raise SystemExit(f"--checkpoint {checkpoint!r} is not a VLA folder: run `infinirl train sft_vla_metaworld` "
                         "first (it writes runs/sft_vla_metaworld/policy) or pass --checkpoint DIR")
    num_envs = args.num_envs or setup["num_envs"]

    import numpy as np
    import torch

    from infinirl.components.embodied_policy import policy_kwargs
    from infinirl.components.embodied_rollout import array_obs
    from infinirl.engines.cpu_dtype import cpu_bf16_is_fast
    from infinirl.envs import make_env
    from infinirl.models.policies.base import build_policy, prepare_obs

    threads = args.threads or setup["threads"] or os.cpu_count() or 1
    torch.set_num_threads(threads)
    env = make_env(setup["env"], num_envs, num_workers=1, seed=0, **setup["env_kwargs"])
    try:
        observations = [prepare_obs(array_obs(env.reset(seeds=list(range(b * num_envs, (b + 1) * num_envs)))), "cpu")
                        for b in range(args.warmup + args.batches)]
        spec, space = env.observation_spec, env.action_space
    finally:
        env.close()
    policies = {}
    for row in ROWS:
        options = {**setup["options"], "checkpoint": checkpoint, "dtype": row}
        torch.manual_seed(0)
        policies[row] = build_policy(setup["policy"], **policy_kwargs(setup["policy"], options, spec, space,
                                                                        setup["chunk"]))
    dtypes = {row: weights_dtype(policies[row]) for row in ROWS}
    config = {"config": args.config, "checkpoint": checkpoint, "env": setup["env"], "num_envs": num_envs,
              "policy": setup["policy"], "threads": threads, "batches": args.batches}
    failed = dtype_failures(dtypes)
    if failed:  # timing two rows of the same dtype would report a ratio that means nothing
        results = {row: {"dtype": dtypes[row], **({"failed": failed[row]} if row in failed else {})} for row in ROWS}
        return conclude({"benchmark": "vla_dtype", "ratios": {"vla_act_bf16_vs_fp32": None},
                         "device": device_description(), "cpu_bf16_native": cpu_bf16_is_fast(), "results": results,
                         "config": config}, failures_of(results))
    seconds: dict[str, list[float]] = {row: [] for row in ROWS}
    actions: dict[str, list[np.ndarray]] = {row: [] for row in ROWS}
    with torch.no_grad():
        for index, obs in enumerate(observations):
            for row in ROWS:  # turn by turn: a slow spell lands on both rows
                start = time.perf_counter()
                step = policies[row].act(obs, deterministic=True)
                elapsed = time.perf_counter() - start
                if index >= args.warmup:
                    seconds[row].append(elapsed)
                    actions[row].append(step.actions.float().numpy())
    results = {row: {"dtype": dtypes[row], **summarise(seconds[row], num_envs)} for row in ROWS}
    gap = np.abs(np.concatenate(actions["bfloat16"]) - np.concatenate(actions["float32"]))
    results["bfloat16"]["action_abs_diff_mean"] = round(float(gap.mean()), 5)
    results["bfloat16"]["action_abs_diff_max"] = round(float(gap.max()), 5)
    ratio = results["bfloat16"]["decisions_per_s"] / results["float32"]["decisions_per_s"]
    final = {"benchmark": "vla_dtype", "ratios": {"vla_act_bf16_vs_fp32": round(ratio, 3)},
             "device": device_description(), "cpu_bf16_native": cpu_bf16_is_fast(), "results": results,
             "config": config}
    for row in ROWS:
        print(f"{row:>9}: {results[row]['decisions_per_s']:8.2f} decisions/s (median {results[row]['median_s']} s "
              f"a call of {num_envs} envs)")
    print(f"bf16 actions vs float32: mean |diff| {results['bfloat16']['action_abs_diff_mean']}, "
          f"max {results['bfloat16']['action_abs_diff_max']} (env action units)")
    return conclude(final, record=(args.record, "VLA acting in bfloat16 vs float32"))


if __name__ == "__main__":
    sys.exit(concluded("vla_dtype", main))
