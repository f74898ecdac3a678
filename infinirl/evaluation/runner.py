"""`infinirl eval`: greedy accuracy, pass@1 and pass@k of a model or a training checkpoint.

Read top to bottom: load the problems (errors here are config errors, before Ray starts), start
the rollout and reward workers, and for a checkpoint build an actor exactly as the run did, load
its weights and sync them into the rollout engine (then free the actor). Generate, score, write
the results JSON atomically, print the summary as one JSON line.
"""

from __future__ import annotations

import json
import time

from infinirl.config import to_plain
from infinirl.engines.base import SamplingParams
from infinirl.evaluation.config import EvalConfig, EvalPlan
from infinirl.evaluation.evaluator import Evaluator, per_problem_records, summarize
from infinirl.runners import register_runner
from infinirl.tasks.problem import Problem
from infinirl.tasks.sources import eval_problems
from infinirl.utils import write_json_atomic


@register_runner("eval", EvalConfig, "greedy accuracy, pass@1 and pass@k of a model or a run's checkpoint")
def run(cfg: EvalConfig) -> dict:
    from infinirl.components.reward import RewardWorker
    from infinirl.components.rollout import RolloutWorker
    from infinirl.runtime import Cluster, WorkerGroup, place

    start = time.perf_counter()
    plan = cfg.resolve()
    problems = load_problems(plan, cfg.split, cfg.limit)
    tokenizer = _tokenizer(plan.model_path)
    engine_options = rollout_engine_options(cfg, plan, problems, tokenizer)
    components = ["rollout", "reward"] + (["actor"] if plan.checkpoint else [])
    with Cluster(cfg.cluster) as cluster:
        placement = place(cluster.inventory, {c: cfg.placement[c] for c in components}, components=components)
        print(placement.describe(), flush=True)
        rollout = WorkerGroup.launch(RolloutWorker, "rollout", placement=placement.ranks("rollout"),
                                     args=(plan.model_path, cfg.model.rollout_dtype, cfg.rollout.max_batch_size,
                                           cfg.num_threads, cfg.rollout.engine, engine_options, plan.agent))
        reward = WorkerGroup.launch(RewardWorker, "reward", placement=placement.ranks("reward"),
                                    args=(plan.model_path, plan.verifier, 0.0))
        try:
            digest = load_checkpoint_into(rollout, plan, placement, cfg.num_threads) if plan.checkpoint else None
            evaluator = Evaluator(rollout, reward, tokenizer, plan.task.system_prompt, cfg.rollout.max_batch_size,
                                  progress=cfg.progress, few_shot=plan.task.few_shot,
                                  with_problems=plan.agent is not None)
            passes = evaluator.run(problems, sampling_passes(cfg, plan))
        finally:
            for group in (rollout, reward):
                group.shutdown()
    metrics = summarize(passes, cfg.ks)
    summary = {
        "output": str(plan.output), "model": plan.model_path,
        "run_dir": str(plan.run_dir) if plan.run_dir else None,
        "checkpoint": str(plan.checkpoint) if plan.checkpoint else None, "step": plan.step,
        "weights_sha256": digest, "weight_versions": sorted(set().union(*(p.weight_versions for p in passes.values()))),
        "task": plan.task.name, "verifier": plan.verifier, "problems": len(problems),
        "samples": cfg.samples, **metrics, "seconds": round(time.perf_counter() - start, 1),
    }
    report = {**summary, "config": to_plain(cfg), "task_config": to_plain(plan.task),
              "max_new_tokens": plan.max_new_tokens}
    if cfg.per_problem:
        report["per_problem"] = per_problem_records(problems, passes)
    plan.output.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(str(plan.output), report)
    print(json.dumps(summary), flush=True)
    return summary


def sampling_passes(cfg: EvalConfig, plan: EvalPlan) -> dict[str, SamplingParams]:
    common = {"max_new_tokens": plan.max_new_tokens, "stop_strings": tuple(plan.stop_strings)}
    passes = {}
    if cfg.greedy:
        passes["greedy"] = SamplingParams(n=1, greedy=True, **common)
    if cfg.samples:
        passes["sampled"] = SamplingParams(n=cfg.samples, temperature=cfg.temperature, top_p=cfg.top_p,
                                           top_k=cfg.top_k, seed=cfg.seed, **common)
    return passes


def rollout_engine_options(cfg: EvalConfig, plan: EvalPlan, problems: list[Problem], tokenizer) -> dict:
    """The rollout engine's options. A vLLM engine gets a ``max_model_len`` that holds the longest
    prompt plus the response budget (or the one set, if that holds it: else a ConfigError, before
    any worker starts, rather than a request refused mid-evaluation)."""
    if cfg.rollout.engine != "vllm":
        return dict(cfg.rollout.engine_options)
    from infinirl.agents.loop import request_context
    from infinirl.engines.vllm_options import check_context_length, with_context_length
    from infinirl.tasks.prompts import encode_prompts

    prompts = encode_prompts(problems, tokenizer, plan.task.system_prompt, few_shot=plan.task.few_shot)
    longest = max((len(ids) for ids in prompts), default=0)
    needed, how = request_context(("the longest prompt", longest), ("max_new_tokens", plan.max_new_tokens),
                                  plan.agent)
    check_context_length(cfg.rollout.engine_options, "rollout.engine_options", needed, how)
    return with_context_length("vllm", cfg.rollout.engine_options, needed)


def load_problems(plan: EvalPlan, split: str, limit: int | None) -> list[Problem]:
    """The evaluation problems; a bad task (unknown generator, missing row key) is a ConfigError."""
    return eval_problems(plan.task, split, limit, from_run=plan.task_from_run)


def load_checkpoint_into(rollout, plan: EvalPlan, placement, num_threads: int) -> str:
    """Build the run's actor, load the checkpoint, sync its weights into ``rollout``; returns the
    SHA-256 of the loaded weights (the digest a training run reports for its actor)."""
    from infinirl.algorithms.objective import PolicyObjectiveConfig
    from infinirl.components.actor import ActorWorker
    from infinirl.runtime import WorkerGroup, sync_weights

    actor = WorkerGroup.launch(ActorWorker, "actor", placement=placement.ranks("actor"),
                               args=(plan.model_path, plan.actor, PolicyObjectiveConfig(), num_threads))
    try:
        actor.load_checkpoint(str(plan.checkpoint / "actor")).wait()
        digest = actor.weights_digest().wait()[0]
        sync_weights(actor, rollout, version=plan.step or 0)
        print(f"loaded {plan.checkpoint} (weights sha256 {digest[:12]}...)", flush=True)
        return digest
    finally:
        actor.shutdown()  # eval needs no trainer: give its memory back before generating


def _tokenizer(model_path: str):
    from transformers import AutoTokenizer

    from infinirl.models.hf_causal_lm import resolve_model_source

    tokenizer = AutoTokenizer.from_pretrained(resolve_model_source(model_path))
    if tokenizer.pad_token_id is None:
        tokenizer.pad_token = tokenizer.eos_token
    return tokenizer
