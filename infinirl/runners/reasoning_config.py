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
    stream_chunk_prompts: int = 0
    """Prompts per streamed chunk: a rollout rank puts each finished chunk into the reward stage's
    channel while it generates the next (0 = one chunk per rollout rank). Small chunks overlap
    scoring with generation; on a CPU, where decoding a batch of 64 costs little more than one of
    32, one chunk per rank is fastest."""
    engine: str = "hf"
    """Inference engine by registered name: hf (transformers, runs anywhere) | vllm (optional extra)."""
    engine_options: dict[str, Any] = field(default_factory=dict)
    """Extra keyword options passed to the engine's constructor."""
    max_prompt_length: int = 1024
    """Longest prompt (tokens, chat template and system prompt included) the run accepts. A longer
    training or eval prompt stops the run with an error naming it, rather than silently eating
    the context window (prompt + max_new_tokens must fit the model) or the KV-cache memory."""


@dataclass
class AlgorithmConfig:
    advantage: str = "grpo"
    """grpo | dr_grpo | rloo | reinforce_pp | reinforce_pp_baseline | gae (PPO: trains a critic,
    see `critic.*`)."""
    advantage_kwargs: dict[str, float] = field(default_factory=dict)
    """Estimator hyperparameters, e.g. `{gamma: 1.0, lam: 0.95}` for gae."""
    whiten_advantages: bool = False
    """Whiten advantages over all response tokens of the batch (zero mean, unit variance) after
    estimation, as PPO implementations usually do for GAE."""
    kl_reward_coef: float = 0.0
    """KL as a reward penalty (InstructGPT-style PPO): every response token gets reward
    `-kl_reward_coef * KL(pi_old || pi_ref)`, which the estimator folds into returns. Needs a
    reference policy (see `reference.*`) and a token-level estimator (gae, reinforce_pp*); the
    loss-term alternative is `objective.kl_coef`. 0 disables it."""
    kl_reward_estimator: str = "k1"
    """KL estimator of the reward penalty: k1 (the log-ratio, as InstructGPT) | k2 | k3."""
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
class CriticConfig(TrainEngineConfig):
    """The PPO critic (used when `algorithm.advantage=gae`): a value model trained alongside the
    actor on the same mini-batches, with its own optimizer. Every engine key of `actor.*` works
    here too (lr, micro_batch_size, lora, param_dtype, ...)."""

    lr: float = 1e-5
    """Peak learning rate of the critic (AdamW); critics usually take ~10x the actor's."""
    model_path: str | None = None
    """Model folder the critic starts from (backbone + a new zero-initialised value head); None:
    the policy's `model.path`."""
    value_clip: float | None = 0.5
    """PPO value clipping: a value moves at most this far from its pre-update estimate per batch
    (the loss takes the worse of clipped and unclipped); None disables it. Only bites with
    several updates per batch (`algorithm.mini_batches`/`epochs` > 1)."""


@dataclass
class ReferenceConfig:
    """The reference policy for the KL terms (`algorithm.objective.kl_coef` or
    `algorithm.kl_reward_coef` > 0): a frozen copy of the initial policy. Unused otherwise."""

    mode: Literal["auto", "actor_base", "separate"] = "auto"
    """actor_base: the LoRA actor's own base model with the adapter switched off (no second copy
    of the weights; needs `actor.lora`). separate: a `reference` component with its own weights and
    placement (`placement.reference`, default: the actor's devices). auto: actor_base when the
    actor uses LoRA, else separate."""
    micro_batch_size: int | None = None
    """Sequences per forward of a separate reference; None: `actor.micro_batch_size`."""


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
    critic: CriticConfig = field(default_factory=CriticConfig)
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)
    placement: dict[str, str] = field(default_factory=lambda: {"actor": "0", "rollout": "0", "reward": "0"})
    """Component -> devices (or CPU slots), see infinirl.runtime.placement. actor, rollout and
    reward are required; critic and a separate reference default to the actor's spec."""
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    # ------------------------------------------------------------------ derived
    @property
    def uses_critic(self) -> bool:
        return self.algorithm.advantage == "gae"

    @property
    def reference_mode(self) -> str | None:
        """How reference log-probs are computed: 'actor_base', 'separate', or None (no KL term)."""
        if self.algorithm.objective.kl_coef <= 0 and self.algorithm.kl_reward_coef <= 0:
            return None
        if self.reference.mode != "auto":
            return self.reference.mode
        return "actor_base" if self.actor.lora is not None else "separate"

    def components(self) -> list[str]:
        """The components this run launches, in launch order."""
        names = ["actor", "rollout", "reward"]
        if self.uses_critic:
            names.append("critic")
        if self.reference_mode == "separate":
            names.append("reference")
        return names

    def placement_spec(self) -> dict[str, str]:
        """One entry per launched component (keys like 'actor,rollout' expanded; critic and
        reference fall back to the actor's spec)."""
        entries = _placement_entries(self.placement)
        for name in ("critic", "reference"):
            entries.setdefault(name, entries["actor"])
        return {name: entries[name] for name in self.components()}

    def validate(self) -> None:
        from infinirl.algorithms import ADVANTAGES, AGGREGATIONS, KL_ESTIMATORS
        from infinirl.engines.registry import ROLLOUT_ENGINES
        from infinirl.runners.metrics_log import KNOWN_LOGGERS
        from infinirl.runtime.placement import PlacementError, parse_spec

        _check_model_path(self.model.path)
        for key in ("steps", "prompts_per_step"):
            if getattr(self, key) <= 0:
                raise ConfigError(f"{key}={getattr(self, key)} must be > 0")
        if self.rollout.stream_chunk_prompts < 0:
            raise ConfigError(f"rollout.stream_chunk_prompts={self.rollout.stream_chunk_prompts} must be >= 0 "
                              "(0 = one chunk per rollout rank)")
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
        if self.rollout.max_prompt_length < 1:
            raise ConfigError(f"rollout.max_prompt_length={self.rollout.max_prompt_length} must be >= 1")
        self._validate_ppo_parts(KL_ESTIMATORS)
        for name in self.loggers:
            if name not in KNOWN_LOGGERS:
                raise ConfigError(f"loggers: unknown logger '{name}'; choose from {', '.join(KNOWN_LOGGERS)}")
        entries = _placement_entries(self.placement)
        missing = {"actor", "rollout", "reward"} - set(entries)
        if missing:
            raise ConfigError(f"placement must place actor, rollout and reward; missing {sorted(missing)}")
        for component, spec in entries.items():
            if component not in KNOWN_COMPONENTS:
                raise ConfigError(
                    f"placement.{component}: unknown component; the reasoning runner has {', '.join(KNOWN_COMPONENTS)}"
                )
            try:
                parse_spec(spec, component)
            except PlacementError as exc:
                raise ConfigError(f"placement.{component}: {exc}") from None

    def _validate_ppo_parts(self, kl_estimators) -> None:
        """Critic, reference and KL keys: values that cannot work, and combinations that would
        silently do nothing."""
        algo = self.algorithm
        if algo.objective.kl_coef < 0:
            raise ConfigError(f"algorithm.objective.kl_coef={algo.objective.kl_coef} must be >= 0 (0 = off)")
        if algo.kl_reward_coef < 0:
            raise ConfigError(f"algorithm.kl_reward_coef={algo.kl_reward_coef} must be >= 0 (0 = off)")
        if algo.kl_reward_estimator not in kl_estimators:
            raise ConfigError(
                f"algorithm.kl_reward_estimator={algo.kl_reward_estimator!r} is not registered; "
                f"registered: {', '.join(kl_estimators.names())}"
            )
        if algo.kl_reward_coef > 0 and algo.advantage in SEQUENCE_LEVEL_ESTIMATORS:
            raise ConfigError(
                f"algorithm.kl_reward_coef > 0 with algorithm.advantage={algo.advantage}: this estimator uses one "
                "reward per sequence and would ignore the per-token KL penalty; use algorithm.objective.kl_coef "
                "(KL as a loss term) instead, or a token-level estimator (gae, reinforce_pp, reinforce_pp_baseline)"
            )
        if self.reference.mode == "actor_base" and self.actor.lora is None:
            raise ConfigError(
                "reference.mode=actor_base needs actor.lora: without adapters the actor's own weights train, so "
                "its base is not the initial policy; use reference.mode=separate (or auto)"
            )
        if self.reference.micro_batch_size is not None and self.reference.micro_batch_size < 1:
            raise ConfigError(f"reference.micro_batch_size={self.reference.micro_batch_size} must be >= 1 (or null)")
        if self.critic.value_clip is not None and self.critic.value_clip <= 0:
            raise ConfigError(f"critic.value_clip={self.critic.value_clip} must be > 0 (or null to disable clipping)")
        if self.critic.lr <= 0:
            raise ConfigError(f"critic.lr={self.critic.lr} must be > 0")
        if self.critic.model_path is not None:
            _check_model_path(self.critic.model_path, key="critic.model_path")
        if self.uses_critic:
            for key in ("gamma", "lam"):
                value = algo.advantage_kwargs.get(key, 1.0)
                if not 0.0 <= value <= 1.0:
                    raise ConfigError(f"algorithm.advantage_kwargs.{key}={value} must be in [0, 1]")
            unknown = set(algo.advantage_kwargs) - {"gamma", "lam"}
            if unknown:
                raise ConfigError(
                    f"algorithm.advantage_kwargs: gae takes gamma and lam, not {', '.join(sorted(unknown))}"
                )

    @property
    def critic_model_path(self) -> str:
        return self.critic.model_path or self.model.path


#: Components the reasoning runner knows (placement keys).
KNOWN_COMPONENTS = ("actor", "rollout", "reward", "critic", "reference")
#: Estimators that read one reward per sequence (ignoring per-token rewards such as a KL penalty).
SEQUENCE_LEVEL_ESTIMATORS = ("grpo", "dr_grpo", "rloo")


def _placement_entries(placement: dict[str, str]) -> dict[str, str]:
    """Expand keys naming several components ('actor,rollout': '0') into one entry each."""
    entries: dict[str, str] = {}
    for key, spec in placement.items():
        for name in (part.strip() for part in str(key).split(",")):
            if not name:
                raise ConfigError(f"placement key {key!r} has an empty component name")
            if name in entries:
                raise ConfigError(f"placement gives {name!r} twice; give each component one entry")
            entries[name] = spec
    return entries


def _check_model_path(path: str, key: str = "model.path") -> None:
    """Fail at validation (not inside a worker) for a model folder that does not exist."""
    from pathlib import Path

    from infinirl.models.smollm2 import MODEL_NAME

    looks_like_hub_id = path.count("/") == 1 and not path.startswith((".", "/", "~"))
    if path != MODEL_NAME and not looks_like_hub_id and not Path(path).expanduser().is_dir():
        raise ConfigError(
            f"{key}={path!r} is not a folder; pass a local Hugging Face model folder or the "
            f"embedded default '{MODEL_NAME}'"
        )
