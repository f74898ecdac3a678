"""Benchmark: seconds per GRPO step, InfiniRL vs TRL's GRPOTrainer, same settings, one machine.

Both train SmolLM2-135M-Instruct on reasoning-gym chain_sum (two 1-digit terms) with 8 prompts x 8
completions, <= 48 new tokens, lr 1e-5, no KL, one policy update per batch, for ``--steps`` steps,
each in its own subprocess (so neither sees the other's memory or threads). Reported per impl:
median seconds per step (first step excluded as warm-up when there are >= 3), generated tokens/s
and the final training reward. ``--precision`` applies to both (fp32 = TRL's CPU default).

The row ``infinirl_async`` runs InfiniRL asynchronously (``algorithm.asynchronous.max_staleness=1``,
decoupled PPO with ``is_cap=2, is_cap_mode=mask``): the next batch is generated while the actor
trains on this one. Actor and rollout then run at the same time; ``--async-threads A,R`` sets their
torch threads (default: all the cores for the actor, whose update fills most of the step, and half
for the rollout).

When vLLM is installed, a row ``infinirl_vllm`` runs InfiniRL with ``rollout.engine=vllm``.
vLLM lives in its own venv (``bash scripts/setup_vllm_venv.sh``), so that row runs under the first
interpreter that can import it: this one, ``$INFINIRL_VLLM_PYTHON``, or the script's default venv.

    pip install trl            # the baseline (not a dependency of infinirl)
    python benchmarks/grpo_vs_trl.py --steps 4
    python benchmarks/grpo_vs_trl.py --steps 4 --impls infinirl,infinirl_vllm   # skip TRL

Last stdout line: {"benchmark": "grpo_vs_trl", "ratios": {"step_speed_vs_trl": TRL s/step / ours},
"targets": {"step_speed_vs_trl": 1.5, "step_speed_vs_trl_async": 2.5}, "device": ..., "results": {...}};
ratios also has "step_speed_vs_trl_async" (TRL s/step / the asynchronous row's), and with the vLLM
row "step_speed_vllm_vs_trl" and "step_speed_vllm_vs_hf" (HF-engine s/step / vLLM-engine).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench_common import add_record_argument, record_result

TASK = {"min_terms": 2, "max_terms": 2, "min_digits": 1, "max_digits": 1}
PROMPTS, GROUP, MAX_NEW, LR = 8, 8, 48, 1e-5
MICRO_BATCH = int(os.environ.get("INFINIRL_BENCH_MICRO_BATCH", 16))  # sequences per forward/backward (ours)
IMPLS = ("infinirl", "infinirl_async", "trl", "infinirl_vllm")
DEFAULT_VLLM_VENV = Path(os.environ.get("INFINIRL_CACHE", Path.home() / ".cache" / "infinirl")) / "vllm-venv"


def vllm_python() -> str | None:
    """An interpreter that can import vllm: this one, $INFINIRL_VLLM_PYTHON, or the setup script's
    venv; None when vLLM is not installed anywhere we look."""
    if importlib.util.find_spec("vllm") is not None:
        return sys.executable
    candidates = [os.environ.get("INFINIRL_VLLM_PYTHON"), str(DEFAULT_VLLM_VENV / "bin" / "python")]
    for python in filter(None, candidates):
        if os.path.isfile(python):
            has_vllm = "import importlib.util as u, sys; sys.exit(u.find_spec('vllm') is None)"
            probe = subprocess.run([python, "-c", has_vllm], capture_output=True)
            if probe.returncode == 0:
                return python
    return None


def run_infinirl(steps: int, precision: str, out: str, engine: str = "hf",
                 async_threads: tuple[int, int] | None = None) -> dict:
    """``async_threads``: run asynchronously, with these torch threads for the actor and the rollout."""
    from infinirl.config import to_dataclass
    from infinirl.runners.reasoning import run
    from infinirl.runners.reasoning_config import ReasoningConfig

    threads = rollout_threads = os.cpu_count()
    algorithm = {}
    if async_threads:
        threads, rollout_threads = async_threads
        algorithm = {"asynchronous": {"max_staleness": 1}, "objective": {"is_cap": 2.0, "is_cap_mode": "mask"}}
    cfg = to_dataclass(ReasoningConfig, {
        "iterations": steps, "prompts_per_step": PROMPTS, "eval": {"every": 10_000}, "output_dir": out,
        "resume": False, "loggers": [], "num_threads": threads,
        "model": {"rollout_dtype": precision},
        "task": {"config": TASK, "eval_size": 1},
        "rollout": {"group_size": GROUP, "max_new_tokens": MAX_NEW, "max_batch_size": PROMPTS * GROUP,
                    "engine": engine, "num_threads": rollout_threads},
        "actor": {"lr": LR, "micro_batch_size": MICRO_BATCH, "param_dtype": precision},
        "algorithm": algorithm,
        "cluster": {"log_to_driver": False},
    })
    run(cfg)
    rows = [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl"))]
    steps_rows = [r for r in rows if "time/step_s" in r]
    return {
        "step_s": [r["time/step_s"] for r in steps_rows],
        "tokens_per_s": [r["rollout/tokens_per_s"] for r in steps_rows],
        "final_reward": steps_rows[-1]["rollout/reward_mean"],
    }


def run_trl(steps: int, precision: str, out: str) -> dict:
    import torch
    from datasets import Dataset
    from transformers import AutoModelForCausalLM, AutoTokenizer, TrainerCallback
    from trl import GRPOConfig, GRPOTrainer

    from infinirl.models.smollm2 import ensure_converted
    from infinirl.tasks.reasoning_gym_tasks import ReasoningGymStream, ReasoningGymTask
    from infinirl.tasks.verifiers import build_verifier, safe_score

    torch.set_num_threads(os.cpu_count())
    folder = ensure_converted()
    stream = ReasoningGymStream(ReasoningGymTask("chain_sum", TASK), seed=0)
    problems = stream.next_batch(PROMPTS * (steps + 1))
    by_prompt = {p.prompt: p for p in problems}
    dataset = Dataset.from_list([{"prompt": [{"role": "user", "content": p.prompt}]} for p in problems])
    verifier = build_verifier("reasoning_gym")

    def reward(prompts, completions, **_):
        return [safe_score(c[0]["content"], by_prompt[p[-1]["content"]], verifier).reward
                for p, c in zip(prompts, completions)]

    times, tokens = [], []

    class Timer(TrainerCallback):
        def on_step_begin(self, args, state, control, **kw):
            self.start = time.perf_counter()

        def on_step_end(self, args, state, control, **kw):
            times.append(time.perf_counter() - self.start)

        def on_log(self, args, state, control, logs=None, **kw):
            if logs and "completions/mean_length" in logs:
                tokens.append(logs["completions/mean_length"])

    config = GRPOConfig(
        output_dir=out, max_steps=steps, learning_rate=LR, per_device_train_batch_size=PROMPTS * GROUP,
        num_generations=GROUP, max_completion_length=MAX_NEW, beta=0.0, num_iterations=1,
        use_cpu=True, bf16=precision == "bfloat16", logging_steps=1, report_to=[], save_strategy="no",
        temperature=1.0, shuffle_dataset=False, dataloader_num_workers=0,
    )
    model = AutoModelForCausalLM.from_pretrained(folder, dtype=torch.float32)
    trainer = GRPOTrainer(model=model, reward_funcs=reward, args=config, train_dataset=dataset,
                          processing_class=AutoTokenizer.from_pretrained(folder), callbacks=[Timer()])
    trainer.train()
    rewards = [h["reward"] for h in trainer.state.log_history if "reward" in h]
    return {"step_s": times, "mean_completion_tokens": tokens, "final_reward": rewards[-1] if rewards else None}


def _median_step(step_s: list[float]) -> float:
    body = step_s[1:] if len(step_s) >= 3 else step_s
    return statistics.median(body)


def _async_threads(parser, text: str | None) -> tuple[int, int]:
    cores = os.cpu_count() or 2
    # The update fills most of the step: it keeps every core, generation beside it takes half.
    threads = tuple(int(n) for n in text.split(",")) if text else (cores, max(1, cores // 2))
    if len(threads) != 2 or min(threads) < 1:
        parser.error(f"--async-threads {text!r}: give two positive counts, actor and rollout (e.g. 2,1)")
    return threads


def _run_row(impl: str, python: str, args, async_threads) -> dict:
    start = time.perf_counter()
    proc = subprocess.run([python, __file__, "--only", impl, "--steps", str(args.steps),
                           "--precision", args.precision, "--async-threads", ",".join(map(str, async_threads))],
                          capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode or not lines:
        result = {"skipped": f"exit {proc.returncode}: {proc.stderr[-1500:]}"}
    else:
        result = json.loads(lines[-1][7:])
        result["median_step_s"] = _median_step(result["step_s"])
    result["wall_s"] = round(time.perf_counter() - start, 1)
    if impl == "infinirl_vllm":
        result["python"] = python
    print(f"[{impl}] {json.dumps(result)[:400]}", file=sys.stderr, flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--precision", choices=["float32", "bfloat16"], default="float32")
    parser.add_argument("--impls", default=",".join(IMPLS),
                        help="comma-separated rows to run (infinirl_vllm only runs where vLLM is installed)")
    parser.add_argument("--async-threads", default=None,
                        help="A,R: torch threads of the actor and the rollout in the infinirl_async row "
                             "(default: all the cores, and half)")
    parser.add_argument("--only", choices=IMPLS, help=argparse.SUPPRESS)
    add_record_argument(parser)
    args = parser.parse_args()
    async_threads = _async_threads(parser, args.async_threads)
    if args.only:
        out = tempfile.mkdtemp(prefix=f"bench-{args.only}-")
        if args.only == "trl":
            result = run_trl(args.steps, args.precision, out)
        else:
            result = run_infinirl(args.steps, args.precision, out, "vllm" if args.only == "infinirl_vllm" else "hf",
                                  async_threads=async_threads if args.only == "infinirl_async" else None)
        print("RESULT " + json.dumps(result), flush=True)
        return 0
    wanted = [impl.strip() for impl in args.impls.split(",") if impl.strip()]
    unknown = sorted(set(wanted) - set(IMPLS))
    if unknown:
        parser.error(f"--impls: unknown {unknown}; choose from {', '.join(IMPLS)}")
    pythons = {"infinirl": sys.executable, "infinirl_async": sys.executable, "trl": sys.executable,
               "infinirl_vllm": vllm_python()}
    if pythons["infinirl_vllm"] is None and "infinirl_vllm" in wanted:
        wanted.remove("infinirl_vllm")  # vLLM not installed: no row (see scripts/setup_vllm_venv.sh)
    results = {impl: _run_row(impl, pythons[impl], args, async_threads) for impl in wanted}

    def median(impl):
        return results.get(impl, {}).get("median_step_s")

    def speedup(slow, fast):
        return round(median(slow) / median(fast), 3) if median(slow) and median(fast) else None

    ratios = {"step_speed_vs_trl": speedup("trl", "infinirl")}
    if "infinirl_async" in results:
        ratios["step_speed_vs_trl_async"] = speedup("trl", "infinirl_async")
        ratios["step_speed_async_vs_sync"] = speedup("infinirl", "infinirl_async")
    if "infinirl_vllm" in results:
        ratios["step_speed_vllm_vs_trl"] = speedup("trl", "infinirl_vllm")
        ratios["step_speed_vllm_vs_hf"] = speedup("infinirl", "infinirl_vllm")
    targets = {"step_speed_vs_trl": 1.5, "step_speed_vs_trl_async": 2.5}
    final = {"benchmark": "grpo_vs_trl", "ratios": ratios, "targets": targets,
             "device": f"{platform.processor() or platform.machine()} ({os.cpu_count()} cpus)",
             "precision": args.precision, "async_threads": list(async_threads), "results": results}
    print(json.dumps(final))
    record_result(args.record, "GRPO step against TRL", final)
    return 0


if __name__ == "__main__":
    sys.exit(main())
