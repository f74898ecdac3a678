"""Where the reasoning runner's problems come from: a reasoning-gym generator or a dataset file.

Held-out evaluation is disjoint from training by construction: the eval set is drawn first and
the train stream skips any question in it (generators), or the eval split is a different file.
"""

from __future__ import annotations

from transformers import AutoTokenizer

from infinirl.models.hf_causal_lm import resolve_model_source
from infinirl.tasks.datasets import DATASET_PRESETS, EpochBatchIterator, load_preset, load_problems
from infinirl.tasks.reasoning_gym_tasks import ReasoningGymStream, ReasoningGymTask, build_eval_set


def build_problem_sources(cfg):
    task = cfg.task
    if task.source == "reasoning_gym":
        generator = ReasoningGymTask(task.name, task.config)
        eval_problems = build_eval_set(generator, task.eval_size, seed=task.eval_seed)
        train = ReasoningGymStream(generator, seed=cfg.seed, exclude=eval_problems)
    elif task.name in DATASET_PRESETS:
        train = EpochBatchIterator(load_preset(task.name, "train"), seed=cfg.seed)
        eval_problems = load_preset(task.name, "test", limit=task.eval_size)
    else:
        rows = load_problems(task.name, prompt_key=task.prompt_key, answer_key=task.answer_key, verifier=task.verifier)
        eval_problems, rest = rows[: task.eval_size], rows[task.eval_size :]
        train = EpochBatchIterator(rest, seed=cfg.seed)
    tokenizer = AutoTokenizer.from_pretrained(resolve_model_source(cfg.model.path))
    if tokenizer.pad_token_id is None:
        tokenizer.pad_token = tokenizer.eos_token
    return train, eval_problems, tokenizer
