"""Benchmark: multi-turn agent rollouts with slow tools, many trajectories in flight (``async``)
against the same engine stepping all trajectories in lock-step (``lockstep``: every turn waits for
the slowest tool call of the batch).

Both rows run ``infinirl.agents.loop.AgentRollout`` on the same HF engine, prompts and sampling;
only ``AgentBudget.schedule`` differs. The environment stands in for a tool: each call sleeps a
latency drawn from a log-normal distribution (median ``--tool-ms``, shape ``--tool-sigma``; real
tools (a search API, a code run) have a heavy tail), seeded per trajectory and call so both rows
see the same latencies. By default the model is a tiny random Llama whose turns end at frequent
characters (generation is cheap, as on a GPU, so the tools dominate, as in production agents);
``--model smollm2`` runs the embedded SmolLM2-135M-Instruct on the calculator task instead.

Each row first runs an untimed warm-up rollout (``--warmup-trajectories``: the engine's first calls
and allocations), then the rows run ``--repeats`` times, back to back, the order alternating every
repeat (so neither row always runs first on a machine whose speed drifts); each repeat gives its
own ratio, and the reported ratio is their median.

    python benchmarks/agent_rollout.py                  # a few minutes
    python benchmarks/agent_rollout.py --trajectories 128 --tool-ms 200 --tool-sigma 1.0

The last stdout line is ONE JSON object: {"benchmark": "agent_rollout", "ratios":
{"agent_async_vs_lockstep": median over repeats of async trajectories/s / lockstep trajectories/s},
"per_repeat": {ratio key: [...]}, "targets": {...}, "results": {row: {... "runs": [...]}},
"failures": [...]}.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import statistics
import sys
import time

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import add_record_argument, conclude, concluded, device_description  # noqa: E402

from infinirl.agents.loop import AgentBudget, AgentEnv, AgentRollout, AgentStep  # noqa: E402
from infinirl.engines.base import SamplingParams  # noqa: E402

TARGETS = {"agent_async_vs_lockstep": 2.0}
ROWS = ("lockstep", "async")
TINY_STOPS = tuple("abcdefghijklmnopqrstuvwxyz")


class SlowToolEnv(AgentEnv):
    """Answers each call after a log-normal latency; the trajectory ends after ``calls`` calls."""

    def __init__(self, stops, seed: int, median_s: float, sigma: float, calls: int, inner: AgentEnv | None = None):
        self.stop_strings = stops if inner is None else inner.stop_strings
        self.rng, self.median_s, self.sigma, self.calls = random.Random(seed), median_s, sigma, calls
        self.inner, self.made = inner, 0

    def step(self, turn: str) -> AgentStep:
        time.sleep(self.median_s * math.exp(self.sigma * self.rng.gauss(0.0, 1.0)))
        if self.inner is not None:
            return self.inner.step(turn)
        self.made += 1
        return AgentStep(observation=" [tool output] ", done=self.made > self.calls)


def build_setup(args):
    """(engine, tokenizer, prompts, env factory maker, sampling) for ``args.model``."""
    import torch

    torch.set_num_threads(args.threads)
    if args.model == "tiny":
        from infinirl.engines.hf_generate import HFGenerateEngine
        from infinirl.models.hf_causal_lm import tiny_causal_lm

        model, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
        engine = HFGenerateEngine(model, tokenizer, max_batch_size=args.trajectories, eos_token_ids=[])
        prompts = [[5 + i % 50, 6, 7, 8 + i % 3] for i in range(args.trajectories)]
        inner = None
    else:
        from infinirl.agents.tool_env import ToolEnv
        from infinirl.engines.registry import build_rollout_engine

        engine = build_rollout_engine("hf", "smollm2-135m-instruct", "float32", "cpu", args.trajectories, {})
        tokenizer = engine.tokenizer
        shot = [{"role": "user", "content": "Calculate 12 + 34."},
                {"role": "assistant", "content": "<calculator>12 + 34</calculator><result>\n46\n</result>\n46"}]
        rng = random.Random(0)
        prompts = []
        for _ in range(args.trajectories):
            question = f"Calculate {rng.randint(100, 9999)} * {rng.randint(100, 9999)}."
            messages = [{"role": "system", "content": "Use the calculator: write <calculator>expression</calculator> "
                                                      "and the result appears. Then reply with the final number."},
                        *shot, {"role": "user", "content": question}]
            prompts.append(tokenizer.apply_chat_template(messages, add_generation_prompt=True, tokenize=True,
                                                         return_dict=False))
        inner = ToolEnv
    return engine, tokenizer, prompts, inner


def run_row(schedule: str, args, engine, tokenizer, prompts, inner) -> dict:
    counter = iter(range(10**9))

    def make_env():
        index = next(counter)
        return SlowToolEnv(TINY_STOPS, seed=index, median_s=args.tool_ms / 1000, sigma=args.tool_sigma,
                           calls=args.calls, inner=None if inner is None else inner(tools=["calculator"]))

    budget = AgentBudget(max_turns=args.calls + 2, max_response_tokens=args.max_response_tokens,
                         concurrency=args.trajectories, schedule=schedule)
    sampling = SamplingParams(n=1, max_new_tokens=args.turn_tokens, seed=0)
    rollout = AgentRollout(engine, tokenizer, make_env, budget)
    start = time.perf_counter()
    results = rollout.generate(prompts, sampling)
    wall = time.perf_counter() - start
    stats = [r.extra["agent"] for r in results]
    return {"trajectories": len(results), "wall_s": round(wall, 3),
            "trajectories_per_s": round(len(results) / wall, 3),
            "turns_mean": round(sum(s["turns"] for s in stats) / len(stats), 3),
            "env_steps_mean": round(sum(s["env_steps"] for s in stats) / len(stats), 3),
            "tool_s_sum": round(sum(s["env_s"] for s in stats), 3)}


def row_order(rows: list[str], repeat: int) -> list[str]:
    """The rows of one repeat in run order: as given in even repeats, reversed in odd ones."""
    return list(rows) if repeat % 2 == 0 else list(rows)[::-1]


def summarise_runs(runs: dict[str, list[dict]]) -> tuple[dict, dict, dict]:
    """Per row its median rate over the repeats and every run; per repeat the async/lockstep ratio of
    its two back-to-back runs; and the ratio reported, their median."""
    results = {row: {"trajectories_per_s": round(statistics.median(r["trajectories_per_s"] for r in done), 3),
                     "runs": done} for row, done in runs.items()}
    per_repeat, ratios = {}, {}
    if {"async", "lockstep"} <= set(runs):
        key = "agent_async_vs_lockstep"
        per_repeat[key] = [round(a["trajectories_per_s"] / b["trajectories_per_s"], 3)
                           for a, b in zip(runs["async"], runs["lockstep"])]
        ratios[key] = round(statistics.median(per_repeat[key]), 3)
    return results, per_repeat, ratios


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", choices=("tiny", "smollm2"), default="tiny")
    parser.add_argument("--trajectories", type=int, default=64)
    parser.add_argument("--calls", type=int, default=3, help="tool calls per trajectory (tiny model)")
    parser.add_argument("--tool-ms", type=float, default=200.0, help="median tool latency")
    parser.add_argument("--tool-sigma", type=float, default=1.0, help="log-normal shape of the tool latency")
    parser.add_argument("--turn-tokens", type=int, default=16, help="max new tokens per turn")
    parser.add_argument("--max-response-tokens", type=int, default=160)
    parser.add_argument("--threads", type=int, default=max(1, (os.cpu_count() or 2) // 2))
    parser.add_argument("--rows", default=",".join(ROWS))
    parser.add_argument("--repeats", type=int, default=2, help="timed runs of each row, the order alternating")
    parser.add_argument("--warmup-trajectories", type=int, default=8,
                        help="trajectories of each row's untimed warm-up rollout (0: none)")
    add_record_argument(parser)
    args = parser.parse_args()
    rows = [row.strip() for row in args.rows.split(",") if row.strip()]
    if not rows or set(rows) - set(ROWS):
        parser.error(f"--rows {args.rows!r}: choose from {', '.join(ROWS)}")
    if args.repeats < 1 or args.warmup_trajectories < 0:
        parser.error("--repeats must be >= 1 and --warmup-trajectories >= 0")

    engine, tokenizer, prompts, inner = build_setup(args)
    if args.warmup_trajectories:
        for row in rows:  # untimed: the engine's first calls and allocations
            run_row(row, args, engine, tokenizer, prompts[:args.warmup_trajectories], inner)
    runs: dict[str, list[dict]] = {row: [] for row in rows}
    for repeat in range(args.repeats):
        for row in row_order(rows, repeat):
            runs[row].append(run_row(row, args, engine, tokenizer, prompts, inner))
            print(f"[{row} {repeat}] {json.dumps(runs[row][-1])}", file=sys.stderr, flush=True)
    results, per_repeat, ratios = summarise_runs(runs)
    final = {"benchmark": "agent_rollout", "ratios": ratios, "per_repeat": per_repeat, "targets": TARGETS,
             "device": device_description(), "config": {k: v for k, v in vars(args).items() if k != "record"},
             "results": results}
    return conclude(final, record=(args.record, "Agent rollouts: many trajectories in flight vs lock-step"))


if __name__ == "__main__":
    sys.exit(concluded("agent_rollout", main))
