"""Typed configuration of the reasoning-RL runner (every field is a `key=value` CLI override).

Field limits are declared on the fields; :meth:`ReasoningConfig.check` holds the rules that involve
several fields. The model folder, the verifier and the task's data are checked before any worker
starts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from infinirl.agents.loop import AgentConfig, request_context
from infinirl.algorithms.objective import PolicyObjectiveConfig
from infinirl.config import ConfigError, bounded
from infinirl.engines.train_base import TrainEngineConfig
from infinirl.models.model_paths import check_model_path, model_context_length
from infinirl.runners.async_rollout import AsyncConfig
from infinirl.runners.run_config import EvalSchedule, RunConfig
from infinirl.tasks.config import TaskConfig


@dataclass(kw_only=True)
class ModelConfig:
    path: str = "smollm2-135m-instruct"
    """A local HF model folder, or the embedded default `smollm2-135m-instruct`."""
    rollout_dtype: str = "float32"
    """Inference dtype of the rollout engine (bfloat16 halves memory; fp32 keeps log-probs closest)."""

    def validate(self) -> None:
        from infinirl.engines.cpu_dtype import check_dtype_name

        check_dtype_name(self.rollout_dtype, "model.rollout_dtype")


@dataclass(kw_only=True)
class RolloutConfig:
    group_size: int = bounded(8, ge=1)
    """Samples per prompt (GRPO group)."""
    max_new_tokens: int = bounded(48, ge=1)
    temperature: float = bounded(1.0, gt=0)
    top_p: float = bounded(1.0, gt=0, le=1)
    top_k: int = bounded(0, ge=0)
    stop_strings: list[str] = field(default_factory=list)
    max_batch_size: int = bounded(64, ge=1)
    """Sequences decoded together per rollout rank (bounds KV-cache memory)."""
    num_threads: int = bounded(0, ge=0)
    """torch threads per rollout rank (0 = torch default)."""
    stream_chunk_prompts: int = bounded(0, ge=0)
    """Prompts per streamed chunk: a rollout rank puts each finished chunk into the reward stage's
    channel while it generates the next (0 = one chunk per rollout rank). Small chunks overlap
    scoring with generation; on a CPU, where decoding a batch of 64 costs little more than one of
    32, one chunk per rank is fastest."""
    engine: str = "hf"
    """Inference engine by registered name: hf (transformers, runs anywhere) | vllm (optional extra)."""
    engine_options: dict[str, Any] = field(default_factory=dict)
    """Extra keyword options passed to the engine's constructor."""
    sync_changed_only: bool = True
    """After the first weight sync, send the rollout only the weights training changes (a LoRA
    actor on the top layers: their merged projections, a fifth of SmolLM2-135M's bytes); false:
    every weight each time. The hf engine only (vLLM, and staged partial-rollout syncs, always get
    every weight)."""
    max_prompt_length: int = bounded(1024, ge=1)
    """Longest prompt (tokens, chat template and system prompt included) the run accepts. A longer
    training or eval prompt stops the run with an error naming it, rather than silently eating
    the context window (prompt + max_new_tokens must fit the model) or the KV-cache memory."""
    agent: AgentConfig | None = None
    """Multi-turn rollouts with tools between the model's turns (docs/agents.md); null = one turn.
    With an agent, ``max_new_tokens`` bounds each turn and ``agent.max_response_tokens`` the whole
    trajectory."""


@dataclass(kw_only=True)
class AlgorithmConfig:
    advantage: str = "grpo"
    """grpo | dr_grpo | rloo | reinforce_pp | reinforce_pp_baseline | gae (PPO: trains a critic,
    see `critic.*`)."""
    advantage_kwargs: dict[str, float] = field(default_factory=dict)
    """Estimator hyperparameters, e.g. `{gamma: 1.0, lam: 0.95}` for gae."""
    whiten_advantages: bool = False
    """Whiten advantages over all response tokens of the batch (zero mean, unit variance) after
    estimation, as PPO implementations usually do for GAE."""
    kl_reward_coef: float = bounded(0.0, ge=0)
    """KL as a reward penalty (InstructGPT-style PPO): every response token gets reward
    `-kl_reward_coef * KL(pi_old || pi_ref)`, which the estimator folds into returns. Needs a
    reference policy (see `reference.*`) and a token-level estimator (gae, reinforce_pp*); the
    loss-term alternative is `objective.kl_coef`. 0 disables it."""
    kl_reward_estimator: str = "k1"
    """KL estimator of the reward penalty: k1 (the log-ratio, as InstructGPT) | k2 | k3."""
    objective: PolicyObjectiveConfig = field(default_factory=PolicyObjectiveConfig)
    mini_batches: int = bounded(1, ge=1)
    """Optimizer steps per rollout batch (1 = fully on-policy; old log-probs then need no extra pass)."""
    epochs: int = bounded(1, ge=1)
    dynamic_sampling: bool = False
    """DAPO: drop groups whose rewards are all equal and generate more until the batch is full."""
    max_extra_rounds: int = bounded(3, ge=0)
    overlong_buffer: int = bounded(0, ge=0)
    """DAPO overlong shaping: soft penalty over the last N tokens before the response cap (0 = off).
    The cap is rollout.max_new_tokens, or rollout.agent.max_response_tokens with an agent."""
    overlong_penalty: float = 1.0
    truncated_reward: Literal["keep", "zero"] = "keep"
    """A response cut off at the token cap (finish reason "length"; for an agent, any budget run
    out): keep its verifier's reward, or zero it before advantages (its answer may be a guess the
    cut left standing; logged as `rollout/truncated_zeroed`)."""
    asynchronous: AsyncConfig = field(default_factory=AsyncConfig)
    """Rollout ahead of the trainer by up to `max_staleness` weight versions (see
    docs/reasoning.md#asynchronous-training)."""


@dataclass(kw_only=True)
class CriticConfig(TrainEngineConfig):
    """The PPO critic (used when `algorithm.advantage=gae`): a value model trained alongside the
    actor on the same mini-batches, with its own optimizer. Every engine key of `actor.*` works
    here too (lr, micro_batch_size, lora, param_dtype, ...)."""

    lr: float = bounded(1e-5, gt=0)
    """Peak learning rate of the critic (AdamW); critics usually take ~10x the actor's."""
    model_path: str | None = None
    """Model folder the critic starts from (backbone + a new zero-initialised value head); None:
    the policy's `model.path`."""
    value_clip: float | None = bounded(0.5, gt=0)
    """PPO value clipping: a value moves at most this far from its pre-update estimate per batch
    (the loss takes the worse of clipped and unclipped); None disables it. Only bites with
    several updates per batch (`algorithm.mini_batches`/`epochs` > 1)."""


@dataclass(kw_only=True)
class ReferenceConfig:
    """The reference policy for the KL terms (`algorithm.objective.kl_coef` or
    `algorithm.kl_reward_coef` > 0): a frozen copy of the initial policy. Unused otherwise."""

    mode: Literal["auto", "actor_base", "separate"] = "auto"
    """actor_base: the LoRA actor's own base model with the adapter switched off (no second copy
    of the weights; needs `actor.lora`). separate: a `reference` component with its own weights and
    placement (`placement.reference`, default: the actor's devices). auto: actor_base when the
    actor uses LoRA, else separate."""
    micro_batch_size: int | None = bounded(None, ge=1)
    """Sequences per forward of a separate reference; None: `actor.micro_batch_size`."""


@dataclass(kw_only=True)
class ReasoningEvalConfig(EvalSchedule):
    """Greedy held-out accuracy on task.eval_size problems, every `every` iterations, before the first
    (at_start) and after the last."""


@dataclass(kw_only=True)
class ReasoningConfig(RunConfig):
    RUNNER: ClassVar[str] = "reasoning"
    DEFAULT_PLACEMENT: ClassVar[dict[str, str]] = {"actor": "0", "rollout": "0", "reward": "0"}
    OPTIONAL_COMPONENTS: ClassVar[dict[str, str]] = {"critic": "actor", "reference": "actor"}
    RENAMED_KEYS: ClassVar[dict[str, str]] = {"steps": "iterations", "eval_every": "eval.every",
                                              "algorithm.objective.tis_cap": "algorithm.objective.is_cap"}
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = (
        "num_threads", "rollout.num_threads", "rollout.max_batch_size", "rollout.stream_chunk_prompts",
        "actor.micro_batch_size", "actor.logprob_chunk_tokens", "actor.max_packed_tokens",
        "critic.micro_batch_size", "reference.micro_batch_size",
        # scoring only, nothing checkpointed depends on it: a run written while the trainer scored at 1.0
        # whatever it sampled at resumes scoring at its rollout.temperature (recorded in the config history)
        "actor.temperature")

    output_dir: str = "runs/reasoning"
    prompts_per_step: int = bounded(8, ge=1)
    """Prompts per iteration (each sampled rollout.group_size times)."""
    num_threads: int = bounded(0, ge=0)
    """torch threads per worker (0 = torch default)."""
    eval: ReasoningEvalConfig = field(default_factory=ReasoningEvalConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    actor: TrainEngineConfig = field(default_factory=TrainEngineConfig)
    critic: CriticConfig = field(default_factory=CriticConfig)
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)

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

    def data_files(self) -> dict[str, str]:
        from infinirl.tasks.sources import task_files

        return task_files(self.task)

    def components(self) -> list[str]:
        """The components this run launches, in launch order."""
        names = ["actor", "rollout", "reward"]
        if self.uses_critic:
            names.append("critic")
        if self.reference_mode == "separate":
            names.append("reference")
        return names

    @property
    def critic_model_path(self) -> str:
        return self.critic.model_path or self.model.path

    @property
    def max_response_tokens(self) -> int:
        """The longest a response can be: one generation's cap, or an agent trajectory's (whose
        turns are each capped by ``rollout.max_new_tokens``)."""
        agent = self.rollout.agent
        return agent.max_response_tokens if agent is not None else self.rollout.max_new_tokens

    def rollout_context(self) -> tuple[int, str]:
        """The most tokens one generate call of this run can ask the rollout engine to hold, and
        how that sum is made (``agents.loop.request_context``); a vLLM engine gets it as its
        ``max_model_len`` unless ``rollout.engine_options.max_model_len`` is set."""
        return request_context(("rollout.max_prompt_length", self.rollout.max_prompt_length),
                               ("rollout.max_new_tokens", self.rollout.max_new_tokens), self.rollout.agent)

    # ------------------------------------------------------------------ cross-field rules
    def check(self) -> None:
        from infinirl.algorithms import ADVANTAGES, AGGREGATIONS, KL_ESTIMATORS
        from infinirl.engines.registry import ROLLOUT_ENGINES, check_engine_options

        check_model_path(self.model.path, "model.path")
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
            ("algorithm.kl_reward_estimator", KL_ESTIMATORS, self.algorithm.kl_reward_estimator),
            ("rollout.engine", ROLLOUT_ENGINES, self.rollout.engine),
        ):
            if value not in registry:
                raise ConfigError(f"{key}={value!r} is not registered; registered: {', '.join(registry.names())}")
        check_engine_options(self.rollout.engine, self.rollout.engine_options, "rollout.engine_options")
        self._tie_actor_temperature()
        self._check_kl_and_reference()
        self._check_advantage_kwargs()
        self._check_critic()
        self._check_off_policy()
        self._check_agent()
        self._check_overlong()
        self._check_vllm()
        self._check_context()

    def _tie_actor_temperature(self) -> None:
        """The trainer scores tokens under the distribution the rollout samples them from
        (``logits / rollout.temperature``): scored at another temperature, the gradient is that of
        another policy than the one that sampled, and the gap grows as training sharpens it."""
        sampled, scored = self.rollout.temperature, self.actor.temperature
        if scored == sampled:
            return
        if scored != 1.0:
            raise ConfigError(
                f"actor.temperature={scored} differs from rollout.temperature={sampled}: the trainer must score "
                "tokens under the distribution the rollout samples them from; remove actor.temperature (it "
                "follows rollout.temperature)"
            )
        self.actor.temperature = sampled

    def _check_vllm(self) -> None:
        """What would otherwise stop a vLLM rollout rank at start-up or mid-run (docs/vllm.md)."""
        if self.rollout.engine != "vllm":
            return
        from infinirl.engines.vllm_options import (
            check_context_length,
            check_model_weights,
            check_temperature,
            check_vllm_options,
        )

        key, options = "rollout.engine_options", self.rollout.engine_options
        check_vllm_options(options, key)
        check_temperature(self.rollout.temperature, "rollout.temperature")
        check_context_length(options, key, *self.rollout_context())
        check_model_weights(self.model.path, "model.path")

    def _check_agent(self) -> None:
        if self.rollout.agent is not None:
            self.rollout.agent.check("rollout.agent", self.task.instructions())

    def _check_overlong(self) -> None:
        buffer, cap = self.algorithm.overlong_buffer, self.max_response_tokens
        if buffer > cap:
            key = "rollout.agent.max_response_tokens" if self.rollout.agent is not None else "rollout.max_new_tokens"
            raise ConfigError(f"algorithm.overlong_buffer={buffer} is longer than the response cap {key}={cap}; "
                              f"set it to at most {cap}")

    def _check_context(self) -> None:
        """The longest prompt plus the longest response must fit the model's context, or the engine
        refuses a generation mid-run (an agent's trajectory grows turn by turn)."""
        context, source = model_context_length(self.model.path), "max_position_embeddings of model.path"
        engine_limit = self.rollout.engine_options.get("max_model_len") if self.rollout.engine == "vllm" else None
        if isinstance(engine_limit, int) and (context is None or engine_limit < context):
            context, source = engine_limit, "rollout.engine_options.max_model_len"
        needed = self.rollout.max_prompt_length + self.max_response_tokens
        if context is None or needed <= context:
            return
        key = "rollout.agent.max_response_tokens" if self.rollout.agent is not None else "rollout.max_new_tokens"
        raise ConfigError(
            f"rollout.max_prompt_length={self.rollout.max_prompt_length} + {key}={self.max_response_tokens} = "
            f"{needed} tokens do not fit the model's context ({source}={context}); lower either so they sum to "
            f"at most {context}"
        )

    def _check_off_policy(self) -> None:
        objective, eta = self.algorithm.objective, self.algorithm.asynchronous.max_staleness
        if objective.is_cap is not None and objective.is_cap <= 0:
            raise ConfigError(f"algorithm.objective.is_cap={objective.is_cap} must be > 0 (e.g. 2.0), or null for no "
                              "importance-weight correction")
        if self.algorithm.asynchronous.partial_rollout and (not eta or self.rollout.engine != "hf"):
            raise ConfigError(
                f"algorithm.asynchronous.partial_rollout=true needs max_staleness >= 1 (got {eta}) and "
                f"rollout.engine=hf (got {self.rollout.engine!r}): only then does a weight update meet generations "
                "in flight that it can interrupt; set max_staleness and rollout.engine, or partial_rollout=false"
            )
        if eta is not None and self.algorithm.dynamic_sampling:
            raise ConfigError(
                "algorithm.dynamic_sampling with algorithm.asynchronous: DAPO's extra generation rounds depend on "
                "the rewards of the batch being trained, which the asynchronous pipeline has not seen yet; set "
                "algorithm.asynchronous.max_staleness=null or algorithm.dynamic_sampling=false"
            )

    def _check_kl_and_reference(self) -> None:
        """KL keys that would silently do nothing, and a reference that cannot be the initial policy."""
        algo = self.algorithm
        if algo.objective.kl_coef < 0:
            raise ConfigError(f"algorithm.objective.kl_coef={algo.objective.kl_coef} must be >= 0 (0 = off)")
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

    def _check_critic(self) -> None:
        if self.critic.model_path is not None:
            check_model_path(self.critic.model_path, "critic.model_path")
        if not self.uses_critic:
            return
        kwargs = self.algorithm.advantage_kwargs
        for key in ("gamma", "lam"):
            if not 0.0 <= kwargs.get(key, 1.0) <= 1.0:
                raise ConfigError(f"algorithm.advantage_kwargs.{key}={kwargs[key]} must be in [0, 1]")

    def _check_advantage_kwargs(self) -> None:
        """The estimator's options are read off its signature: a misspelt one would otherwise stop the run
        at its first advantage computation, after every model has loaded."""
        from infinirl.algorithms import ADVANTAGES
        from infinirl.utils.signatures import keyword_names

        name = self.algorithm.advantage
        taken, _ = keyword_names(ADVANTAGES.get(name), skip=("inputs",))
        unknown = sorted(set(self.algorithm.advantage_kwargs) - taken)
        if unknown:
            allowed = ", ".join(sorted(taken)) or "no options"
            raise ConfigError(f"algorithm.advantage_kwargs: {name} takes {allowed}, not {', '.join(unknown)}")


#: Estimators that read one reward per sequence (ignoring per-token rewards such as a KL penalty).
SEQUENCE_LEVEL_ESTIMATORS = ("grpo", "dr_grpo", "rloo")
