"""Benchmark: seconds per GRPO step, InfiniRL vs TRL's GRPOTrainer, same settings, one machine.

Both train SmolLM2-135M-Instruct on reasoning-gym chain_sum (two 1-digit terms) with 8 prompts x 8
completions, <= 48 new tokens, lr 1e-5, no KL, one policy update per batch, for ``--steps`` steps,
each in its own subprocess (so neither sees the other's memory or threads). Reported per impl:
median seconds per step over the measured steps (``measured_step_s``: the first step is always
dropped as warm-up, and in the asynchronous row the last too, which has no next batch to generate
beside its update; hence ``--steps >= 5``, at least three measured steps), every step's seconds
(``step_s``), generated tokens/s and the final training reward. ``--precision`` applies to both
(fp32 = TRL's CPU default), resolved once for this CPU (bfloat16 becomes float32 on a CPU without
native bf16, as InfiniRL's engines do: ``engines/cpu_dtype.py``) and given to every row, so both
sides compute in the same dtype; each row reports the dtype it ran with (``dtype``).

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
"targets": {"step_speed_vs_trl": 1.5, "step_speed_vs_trl_async": 2.5}, "device": ..., "precision":
requested, "effective_precision": what every row ran with, "results": {...}, "failures": [...]};
ratios also has "step_speed_vs_trl_async" (TRL s/step / the asynchronous row's), and with the vLLM
row "step_speed_vllm_vs_trl" and "step_speed_vllm_vs_hf" (HF-engine s/step / vLLM-engine). A row
that fails holds "failed", its ratios are null, and the script exits 1.
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

from _bench_common import add_record_argument, conclude, concluded, failures_of, side_failed

TASK = {"min_terms": 2, "max_terms": 2, "min_digits": 1, "max_digits": 1}
PROMPTS, GROUP, MAX_NEW, LR = 8, 8, 48, 1e-5
MICRO_BATCH = int(os.environ.get("INFINIRL_BENCH_MICRO_BATCH", 16))  # sequences per forward/backward (ours)
IMPLS = ("infinirl", "infinirl_async", "trl", "infinirl_vllm")
#: steps a row runs at least: the first (warm-up) and the asynchronous row's last are dropped, three remain
MIN_STEPS = 5
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
        "dtype": infinirl_dtypes(cfg),
        "step_s": [r["time/step_s"] for r in steps_rows],
        "tokens_per_s": [r["rollout/tokens_per_s"] for r in steps_rows],
        "final_reward": steps_rows[-1]["rollout/reward_mean"],
    }


def infinirl_dtypes(cfg) -> dict[str, str]:
    """The dtypes InfiniRL's actor computes in and its rollout engine loads, by the engines' own rules."""
    import torch

    from infinirl.engines.cpu_dtype import resolve_cpu_dtype
    from infinirl.engines.distributed import compute_dtype, resolve_device_type

    actor = compute_dtype(cfg.actor.param_dtype, torch.device(resolve_device_type(cfg.actor.device)))
    rollout = cfg.model.rollout_dtype if torch.cuda.is_available() else resolve_cpu_dtype(cfg.model.rollout_dtype)
    return {"actor": str(actor).removeprefix("torch."), "rollout": rollout}


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
    dtype = "bfloat16" if trainer.args.bf16 else "float32"  # the autocast of its forward and backward passes
    return {"dtype": {"actor": dtype, "rollout": dtype}, "step_s": times, "mean_completion_tokens": tokens,
            "final_reward": rewards[-1] if rewards else None}


def measured_steps(step_s: list[float], asynchronous: bool) -> list[float]:
    """The steps a row's median is over: never the first (warm-up: first calls, allocations), and in
    the asynchronous row not the last either, which generates no next batch beside its update."""
    body = step_s[1:-1] if asynchronous else step_s[1:]
    if len(body) < MIN_STEPS - 2:
        raise ValueError(f"{len(step_s)} steps leave {len(body)} measured; run --steps >= {MIN_STEPS}")
    return body


def _async_threads(parser, text: str | None) -> tuple[int, int]:
    cores = os.cpu_count() or 2
    # The update fills most of the step: it keeps every core, generation beside it takes half.
    threads = tuple(int(n) for n in text.split(",")) if text else (cores, max(1, cores // 2))
    if len(threads) != 2 or min(threads) < 1:
        parser.error(f"--async-threads {text!r}: give two positive counts, actor and rollout (e.g. 2,1)")
    return threads


def _run_row(impl: str, python: str, args, async_threads, precision: str) -> dict:
    start = time.perf_counter()
    proc = subprocess.run([python, __file__, "--only", impl, "--steps", str(args.steps),
                           "--precision", precision, "--async-threads", ",".join(map(str, async_threads))],
                          capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode or not lines:
        result = side_failed(f"exit {proc.returncode}: {proc.stderr[-1500:]}")
    else:
        result = json.loads(lines[-1][7:])
        try:
            result["measured_step_s"] = measured_steps(result["step_s"], asynchronous=impl == "infinirl_async")
            result["median_step_s"] = statistics.median(result["measured_step_s"])
        except ValueError as error:  # fewer steps than asked (a run stopped early)
            result.update(side_failed(str(error)))
    result["wall_s"] = round(time.perf_counter() - start, 1)
    if impl == "infinirl_vllm":
        result["python"] = python
    print(f"[{impl}] {json.dumps(result)[:400]}", file=sys.stderr, flush=True)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=MIN_STEPS,
                        help=f"GRPO steps per row (>= {MIN_STEPS}: the first, and the asynchronous row's last, "
                             "are not measured)")
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
    if args.steps < MIN_STEPS:
        parser.error(f"--steps {args.steps}: at least {MIN_STEPS} (the first step is warm-up and the asynchronous "
                     "row's last has no generation beside it; neither is measured, and a median needs three)")
    if "trl" in wanted and importlib.util.find_spec("trl") is None:
        parser.error("--impls includes trl, which is not installed here: `pip install trl`, or leave the row out "
                     "(--impls infinirl,infinirl_async)")
    from infinirl.engines.cpu_dtype import resolve_cpu_dtype

    precision = resolve_cpu_dtype(args.precision)  # once, for every row: both sides compute in the same dtype
    if precision != args.precision:
        print(f"--precision {args.precision}: this CPU has no native bf16, so every row runs in {precision} "
              "(INFINIRL_CPU_BF16=1 keeps bfloat16)", file=sys.stderr, flush=True)
    results: dict = {}
    pythons = {"infinirl": sys.executable, "infinirl_async": sys.executable, "trl": sys.executable,
               "infinirl_vllm": vllm_python()}
    if pythons["infinirl_vllm"] is None and "infinirl_vllm" in wanted:
        wanted.remove("infinirl_vllm")
        results["infinirl_vllm"] = {"skipped": "vLLM is not installed (bash scripts/setup_vllm_venv.sh)"}
    for impl in wanted:
        results[impl] = _run_row(impl, pythons[impl], args, async_threads, precision)
    final = {"benchmark": "grpo_vs_trl", "ratios": speed_ratios(results),
             "targets": {"step_speed_vs_trl": 1.5, "step_speed_vs_trl_async": 2.5},
             "device": f"{platform.processor() or platform.machine()} ({os.cpu_count()} cpus)",
             "precision": args.precision, "effective_precision": precision, "async_threads": list(async_threads),
             "results": results}
    return conclude(final, row_failures(results, precision), record=(args.record, "GRPO step against TRL"))


def speed_ratios(results: dict) -> dict:
    """Seconds per step of the slower side over the faster's; null where either row failed."""
    def median(impl):
        return results.get(impl, {}).get("median_step_s")

    def speedup(slow, fast):
        return round(median(slow) / median(fast), 3) if median(slow) and median(fast) else None

    ratios = {"step_speed_vs_trl": speedup("trl", "infinirl")}
    if "infinirl_async" in results:
        ratios["step_speed_vs_trl_async"] = speedup("trl", "infinirl_async")
        ratios["step_speed_async_vs_sync"] = speedup("infinirl", "infinirl_async")
    if "median_step_s" in results.get("infinirl_vllm", {}):
        ratios["step_speed_vllm_vs_trl"] = speedup("trl", "infinirl_vllm")
        ratios["step_speed_vllm_vs_hf"] = speedup("infinirl", "infinirl_vllm")
    return ratios


def row_failures(results: dict, precision: str) -> list[str]:
    """Rows that failed, and rows that computed in another dtype than the one every row was given."""
    failures = failures_of(results)
    failures += [f"{impl}: ran in {row['dtype']}, not {precision} like the other rows"
                 for impl, row in results.items() if "dtype" in row and row["dtype"]["actor"] != precision]
    return failures


if __name__ == "__main__":
    sys.exit(concluded("grpo_vs_trl", main))
