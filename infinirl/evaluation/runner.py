"""`infinirl eval`: greedy accuracy, pass@1 and pass@k of a model or a training checkpoint.

Read top to bottom: the preflight loads the problems and the tokenizer and checks them (errors
here are config errors, before Ray starts; ``infinirl validate`` runs it too), start
the rollout and reward workers, and for a checkpoint build an actor exactly as the run did, load
its weights and sync them into the rollout engine (then free the actor). Generate, score, write
the results JSON atomically, print the summary as one JSON line.
"""

from __future__ import annotations

import json
import time
from typing import Any

from infinirl.config import ConfigError, to_plain
from infinirl.engines.base import SamplingParams
from infinirl.evaluation.config import EvalConfig, EvalPlan
from infinirl.evaluation.evaluator import Evaluator, per_problem_records, summarize
from infinirl.runners import register_runner
from infinirl.tasks.problem import Problem
from infinirl.tasks.sources import eval_problems
from infinirl.utils import write_json_atomic


def preflight(cfg: EvalConfig) -> tuple[EvalPlan, list[Problem], Any]:
    """What the evaluation reads, checked in the driver before any worker starts (``infinirl
    validate`` runs it too): the run's data file against what its checkpoint trained on, the
    problems (a task typo, a missing file, no rows, rows without the prompt or answer key), the
    tokenizer, and every prompt plus ``max_new_tokens`` against the model's context (read from its
    config: no weights are loaded) and a vLLM engine's ``max_model_len``; ``(plan, problems, tokenizer)``."""
    plan = cfg.resolve()
    check_run_data(plan)
    problems = load_problems(plan, cfg.split, cfg.limit)
    tokenizer = _tokenizer(plan.model_path)
    check_context(plan, problems, tokenizer)
    rollout_engine_options(cfg, plan, problems, tokenizer)  # a vLLM context length too short: refused here
    return plan, problems, tokenizer


@register_runner("eval", EvalConfig, "greedy accuracy, pass@1 and pass@k of a model or a run's checkpoint",
                 preflight=preflight)
def run(cfg: EvalConfig) -> dict:
    from infinirl.components.reward import RewardWorker
    from infinirl.components.rollout import RolloutWorker
    from infinirl.runtime import Cluster, WorkerGroup, place

    start = time.perf_counter()
    plan, problems, tokenizer = preflight(cfg)
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


def check_run_data(plan: EvalPlan) -> None:
    """On the run's own data (``plan.task_from_run``), its data file must be the one the checkpoint
    recorded (:mod:`infinirl.runners.run_inputs`): the held-out rows are its first
    ``task.eval_size``, so an edited file would score the checkpoint on rows it may have trained on."""
    from infinirl.runners.checkpoints import STATE_FILE
    from infinirl.runners.run_inputs import data_differences, data_digests, describe_difference
    from infinirl.tasks.sources import task_files

    if not (plan.task_from_run and plan.checkpoint):
        return
    try:
        recorded = json.loads((plan.checkpoint / STATE_FILE).read_text()).get("inputs") or {}
    except (OSError, ValueError, AttributeError):
        return  # a checkpoint from before inputs were recorded (its files are checked by resolve)
    for label, was, now in data_differences(recorded.get("data"), data_digests(task_files(plan.task))):
        raise ConfigError(f"run_dir: {describe_difference(label, was, now, f'{plan.checkpoint} trained on')}; its "
                          "held-out rows would not be the ones the run held out; restore it, or evaluate other data "
                          "by setting task.* keys")


def check_context(plan: EvalPlan, problems: list[Problem], tokenizer) -> None:
    """The longest prompt plus ``max_new_tokens`` fits the model's context (``max_position_embeddings``
    of its config), as the rollout engine will require."""
    from infinirl.models.hf_causal_lm import resolve_model_source
    from infinirl.tasks.prompts import encode_prompts

    try:
        from transformers import AutoConfig

        context = getattr(AutoConfig.from_pretrained(resolve_model_source(plan.model_path)),
                          "max_position_embeddings", None)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"model.path={plan.model_path}: its config.json does not load ({exc})") from None
    if not context:
        return
    prompts = encode_prompts(problems, tokenizer, plan.task.system_prompt, few_shot=plan.task.few_shot)
    longest = max(range(len(prompts)), key=lambda i: len(prompts[i]), default=None)
    if longest is None or len(prompts[longest]) + plan.max_new_tokens <= context:
        return
    length = len(prompts[longest])
    raise ConfigError(f"max_new_tokens={plan.max_new_tokens}: prompt {problems[longest].uid!r} is {length} tokens "
                      f"long (chat template and system prompt included), and with the response it needs "
                      f"{length + plan.max_new_tokens} positions, more than the model's context ({context}, "
                      f"max_position_embeddings of {plan.model_path}); lower max_new_tokens to at most "
                      f"{context - length}, shorten task.system_prompt, or leave such problems out")


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

    try:
        tokenizer = AutoTokenizer.from_pretrained(resolve_model_source(model_path))
    except (OSError, ValueError, TypeError) as exc:
        raise ConfigError(f"model.path={model_path}: no tokenizer loads from it ({' '.join(str(exc).split())[:300]}); "
                          "pass a model folder with its tokenizer files") from None
    if tokenizer.pad_token_id is None:
        tokenizer.pad_token = tokenizer.eos_token
    return tokenizer
