"""Typed configuration of the reasoning-RL runner (every field is a `key=value` CLI override)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from infinirl.algorithms.objective import PolicyObjectiveConfig
from infinirl.config import ConfigError
from infinirl.engines.train_base import TrainEngineConfig
from infinirl.runtime import ClusterConfig


@dataclass
class ModelConfig:
    path: str = "smollm2-135m-instruct"
    """A local HF model folder, or the embedded default `smollm2-135m-instruct`."""
    rollout_dtype: str = "float32"
    """Inference dtype of the rollout engine (bfloat16 halves memory; fp32 keeps log-probs closest)."""


@dataclass
class TaskConfig:
    source: Literal["reasoning_gym", "dataset"] = "reasoning_gym"
    name: str = "chain_sum"
    """reasoning-gym task name, or dataset preset (gsm8k, math500) / JSONL/Parquet path."""
    config: dict[str, Any] = field(default_factory=lambda: {"min_terms": 2, "max_terms": 2, "min_digits": 1, "max_digits": 2})
    """Generator options of the reasoning-gym task."""
    verifier: str = "reasoning_gym"
    """Reward verifier: reasoning_gym | math | gsm8k | a dotted path `pkg.module:function`."""
    format_bonus: float = 0.0
    eval_size: int = 64
    """Held-out problems, excluded from training by question text."""
    eval_seed: int = 1_000_003
    system_prompt: str | None = None
    prompt_key: str = "question"
    answer_key: str = "answer"


@dataclass
class RolloutConfig:
    group_size: int = 8
    """Samples per prompt (GRPO group)."""
    max_new_tokens: int = 48
    temperature: float = 1.0
    top_p: float = 1.0
    top_k: int = 0
    stop_strings: list[str] = field(default_factory=list)
    max_batch_size: int = 64
    """Sequences decoded together per rollout rank (bounds KV-cache memory)."""
    num_threads: int = 0
    """torch threads per rollout rank (0 = torch default)."""
    engine: str = "hf"
    """Inference engine by registered name: hf (transformers, runs anywhere) | vllm (optional extra)."""
    engine_options: dict[str, Any] = field(default_factory=dict)
    """Extra keyword options passed to the engine's constructor."""


@dataclass
class AlgorithmConfig:
    advantage: str = "grpo"
    """grpo | dr_grpo | rloo | reinforce_pp | reinforce_pp_baseline (gae needs a critic)."""
    advantage_kwargs: dict[str, float] = field(default_factory=dict)
    objective: PolicyObjectiveConfig = field(default_factory=PolicyObjectiveConfig)
    mini_batches: int = 1
    """Optimizer steps per rollout batch (1 = fully on-policy; old log-probs then need no extra pass)."""
    epochs: int = 1
    dynamic_sampling: bool = False
    """DAPO: drop groups whose rewards are all equal and generate more until the batch is full."""
    max_extra_rounds: int = 3
    overlong_buffer: int = 0
    """DAPO overlong shaping: soft penalty over the last N tokens before max_new_tokens (0 = off)."""
    overlong_penalty: float = 1.0


@dataclass
class ReasoningConfig:
    runner: str = "reasoning"
    steps: int = 20
    prompts_per_step: int = 8
    seed: int = 0
    output_dir: str = "runs/reasoning"
    eval_every: int = 5
    """Greedy held-out accuracy every N steps (and before the first and after the last)."""
    save_every: int = 0
    """Checkpoint every N steps (0 = only at the end)."""
    resume: bool = True
    """Continue from the latest checkpoint in output_dir if there is one."""
    loggers: list[str] = field(default_factory=lambda: ["tensorboard"])
    num_threads: int = 0
    model: ModelConfig = field(default_factory=ModelConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    actor: TrainEngineConfig = field(default_factory=TrainEngineConfig)
    placement: dict[str, str] = field(default_factory=lambda: {"actor": "0", "rollout": "0", "reward": "0"})
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    def validate(self) -> None:
        from infinirl.algorithms import ADVANTAGES, AGGREGATIONS, KL_ESTIMATORS
        from infinirl.engines.registry import ROLLOUT_ENGINES
        from infinirl.runners.metrics_log import KNOWN_LOGGERS
        from infinirl.runtime.placement import PlacementError, parse_spec

        _check_model_path(self.model.path)
        for key in ("steps", "prompts_per_step"):
            if getattr(self, key) <= 0:
                raise ConfigError(f"{key}={getattr(self, key)} must be > 0")
        if self.rollout.group_size < 1:
            raise ConfigError(f"rollout.group_size={self.rollout.group_size} must be >= 1")
        batch = self.prompts_per_step * self.rollout.group_size
        if batch % self.algorithm.mini_batches:
            raise ConfigError(
                f"algorithm.mini_batches={self.algorithm.mini_batches} does not divide the batch of "
                f"prompts_per_step*group_size={batch} samples; pick a divisor"
            )
        for key, registry, value in (
            ("algorithm.advantage", ADVANTAGES, self.algorithm.advantage),
            ("algorithm.objective.aggregation", AGGREGATIONS, self.algorithm.objective.aggregation),
            ("algorithm.objective.kl_estimator", KL_ESTIMATORS, self.algorithm.objective.kl_estimator),
            ("rollout.engine", ROLLOUT_ENGINES, self.rollout.engine),
        ):
            if value not in registry:
                raise ConfigError(f"{key}={value!r} is not registered; registered: {', '.join(registry.names())}")
        if self.algorithm.advantage == "gae":
            raise ConfigError("algorithm.advantage=gae needs a critic, which this runner does not have yet; use grpo, rloo or reinforce_pp")
        if self.algorithm.objective.kl_coef > 0:
            raise ConfigError("algorithm.objective.kl_coef > 0 needs a reference component, not available yet; set it to 0")
        for name in self.loggers:
            if name not in KNOWN_LOGGERS:
                raise ConfigError(f"loggers: unknown logger '{name}'; choose from {', '.join(KNOWN_LOGGERS)}")
        missing = {"actor", "rollout", "reward"} - set(self.placement)
        if missing:
            raise ConfigError(f"placement must place actor, rollout and reward; missing {sorted(missing)}")
        for component, spec in self.placement.items():
            try:
                parse_spec(spec, component)
            except PlacementError as exc:
                raise ConfigError(f"placement.{component}: {exc}") from None


def _check_model_path(path: str) -> None:
    """Fail at validation (not inside a worker) for a model folder that does not exist."""
    from pathlib import Path

    from infinirl.models.smollm2 import MODEL_NAME

    looks_like_hub_id = path.count("/") == 1 and not path.startswith((".", "/", "~"))
    if path != MODEL_NAME and not looks_like_hub_id and not Path(path).expanduser().is_dir():
        raise ConfigError(
            f"model.path={path!r} is not a folder; pass a local Hugging Face model folder or the "
            f"embedded default '{MODEL_NAME}'"
        )
