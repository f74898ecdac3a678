"""Typed configuration of `infinirl eval`, and what it resolves to before anything starts.

Two ways to name the model: a Hugging Face folder (``model.path``), or a training run
(``run_dir``) whose checkpoint is loaded into an actor built with that run's own actor config
(LoRA, dtypes: read from the ``config.json`` every run writes) and synced into the rollout
engine, exactly as during training. `EvalConfig.resolve` reads the run folder and checks every
path, so a missing run, checkpoint or dataset is a `ConfigError` naming its key, before Ray starts.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from infinirl.agents.loop import AgentConfig
from infinirl.config import ConfigError, bounded, to_dataclass, to_plain
from infinirl.engines.train_base import TrainEngineConfig
from infinirl.models.model_paths import check_model_path
from infinirl.runtime import ClusterConfig
from infinirl.tasks.config import TaskConfig
from infinirl.tasks.sources import task_label, verifier_for

RUN_CONFIG_FILE = "config.json"  # written next to metrics.jsonl by every run
# Checkpoint folders: iter_NNNNNN (and step_NNNNNN, as reasoning runs named them before the shared loop).
_CHECKPOINT_DIR = re.compile(r"^(?:iter|step)_(\d+)$")


@dataclass(kw_only=True)
class EvalModelConfig:
    path: str | None = None
    """Local HF model folder or the embedded `smollm2-135m-instruct`. None: the run's base model
    (with run_dir), else the embedded default. With run_dir, set it only if the base model moved."""
    rollout_dtype: str = "float32"
    """Inference dtype of the rollout engine."""

    def validate(self) -> None:
        from infinirl.engines.cpu_dtype import check_dtype_name

        check_dtype_name(self.rollout_dtype, "model.rollout_dtype")


@dataclass(kw_only=True)
class EvalRolloutConfig:
    engine: str = "hf"
    """Inference engine by registered name: hf | vllm (optional extra)."""
    engine_options: dict[str, Any] = field(default_factory=dict)
    max_batch_size: int = bounded(64, ge=1)
    """Sequences decoded together per rollout rank; one call carries max_batch_size // n prompts."""
    agent: dict[str, Any] | None = None
    """Multi-turn rollouts with tools (the keys of training's ``rollout.agent``). With run_dir the
    keys given are laid over the run's ``rollout.agent`` (so ``rollout.agent.max_turns=2`` keeps the
    run's env and options), else over the agent defaults. None: the run's agent with run_dir, else
    single-turn; ``single_turn=true`` turns it off (the no-tools baseline)."""


@dataclass(kw_only=True)
class EvalConfig:
    runner: str = "eval"
    run_dir: str | None = None
    """A training run's output_dir: evaluate its checkpoint (None: evaluate model.path as is)."""
    checkpoint: str = "latest"
    """With run_dir: latest | an iteration number (40) | a folder name (iter_000040) | a checkpoint path
    | initial (the run's model.path untrained, in the run's setting: the baseline it started from)."""
    model: EvalModelConfig = field(default_factory=EvalModelConfig)
    task: TaskConfig | None = None
    """Problems and verifier (same keys as training). None: the run's task (its held-out set)
    with run_dir, else the default reasoning-gym chain_sum task. Setting any task key replaces the
    whole task, e.g. task.source=dataset task.name=gsm8k; a task naming the run's own data (same
    source, name, config, eval_size and eval_seed: e.g. only system_prompt changed) is still
    evaluated on the run's held-out set only."""
    split: str = "test"
    """Split of a dataset preset (gsm8k: train|test)."""
    limit: int | None = bounded(None, ge=1)
    """Evaluate only the first N problems (None: the whole dataset; reasoning-gym tasks draw
    task.eval_size problems). On a run's own task at most its task.eval_size held-out problems."""
    samples: int = bounded(4, ge=0)
    """Sampled responses per problem for pass@k (0: greedy only, and k is not used)."""
    k: int | list[int] = field(default_factory=lambda: [1, 4])
    """pass@k values to report, each <= samples (unbiased estimator over the samples)."""
    greedy: bool = True
    """Also decode one greedy response per problem: greedy accuracy."""
    temperature: float = 1.0
    top_p: float = bounded(1.0, gt=0, le=1)
    top_k: int = bounded(0, ge=0)
    max_new_tokens: int | None = bounded(None, ge=1)
    """Response cap. None: the run's rollout.max_new_tokens with run_dir, else 256."""
    stop_strings: list[str] | None = None
    """None: the run's rollout.stop_strings with run_dir, else none."""
    seed: int = 0
    """Sampling seed: the same config gives the same samples whatever the number of rollout ranks."""
    output: str | None = None
    """Results JSON. None: <run_dir>/eval/<task>-iter_<N>.json, or runs/eval/<task>-<model>.json,
    with -<hash> before .json when a setting that changes the results differs from its default
    (see `EvalConfig.result_settings`), so evaluations with other settings never overwrite each other."""
    single_turn: bool = False
    """Evaluate without any agent loop, even a run's: one turn, no tools."""
    per_problem: bool = True
    """Write each problem's counts, greedy correctness and greedy response into the results."""
    progress: bool = True
    """tqdm progress bar over generated sequences."""
    num_threads: int = bounded(0, ge=0)
    """torch threads per worker (0 = torch default)."""
    rollout: EvalRolloutConfig = field(default_factory=EvalRolloutConfig)
    placement: dict[str, str] = field(default_factory=lambda: {"actor": "0", "rollout": "0", "reward": "0"})
    """actor (only with run_dir: loads the checkpoint, then exits), rollout (data parallel) and reward."""
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    @property
    def ks(self) -> list[int]:
        return [self.k] if isinstance(self.k, int) else list(self.k)

    def validate(self) -> None:
        from infinirl.engines.registry import ROLLOUT_ENGINES, check_engine_options
        from infinirl.runners.run_config import validate_placement

        if not self.samples and not self.greedy:
            raise ConfigError("samples=0 and greedy=false: nothing to evaluate; set samples>0 or greedy=true")
        for k in self.ks if self.samples else ():  # samples=0: greedy only, no pass@k to report
            if k < 1:
                raise ConfigError(f"k={k}: every k must be >= 1")
            if k > self.samples:
                raise ConfigError(f"k={k} is larger than samples={self.samples}: pass@k needs at least k "
                                  f"samples per problem; raise samples or lower k")
        if self.samples and self.temperature <= 0:
            raise ConfigError(f"temperature={self.temperature}: sampled pass@k needs temperature > 0 "
                              "(greedy accuracy comes from greedy=true)")
        if self.rollout.engine not in ROLLOUT_ENGINES:
            raise ConfigError(f"rollout.engine={self.rollout.engine!r} is not registered; "
                              f"registered: {', '.join(ROLLOUT_ENGINES.names())}")
        check_engine_options(self.rollout.engine, self.rollout.engine_options, "rollout.engine_options")
        plan = self.resolve()
        needed = {"rollout", "reward"} | ({"actor"} if plan.checkpoint else set())
        missing = needed - set(self.placement)
        if missing:
            raise ConfigError(f"placement must place {', '.join(sorted(needed))}; missing {sorted(missing)}")
        validate_placement(self.placement, ("actor", "rollout", "reward"), "eval")
        if plan.agent is not None:
            plan.agent.check("rollout.agent", plan.task.instructions())
        if self.rollout.engine == "vllm":
            self._check_vllm(plan)

    def _check_vllm(self, plan: EvalPlan) -> None:
        """What would otherwise stop a vLLM rollout rank at start-up or mid-run (docs/vllm.md); the
        context length is checked by the runner, once the prompts are known."""
        from infinirl.engines.vllm_options import check_model_weights, check_temperature, check_vllm_options

        check_vllm_options(self.rollout.engine_options, "rollout.engine_options")
        if self.samples:
            check_temperature(self.temperature, "temperature")
        check_model_weights(plan.model_path, "model.path")

    def resolve(self) -> EvalPlan:
        """The run, checkpoint, model, task and output this config names; ConfigError if one is missing."""
        run_dir, checkpoint = _find_checkpoint(self.run_dir, self.checkpoint)
        run = _read_run_config(run_dir) if run_dir else None
        model_path = self.model.path or (run["model"]["path"] if run else "smollm2-135m-instruct")
        check_model_path(model_path, "model.path" if self.model.path or not run else
                         f"model.path (from {run_dir / RUN_CONFIG_FILE})")
        where = str(run_dir / RUN_CONFIG_FILE) if run_dir else ""
        run_task = _convert(TaskConfig, run.get("task"), f"{where}: task") if run else None
        task, max_new, stops, agent = self._with_run_defaults(run, run_task, where)
        verifier = verifier_for(task, self.split)
        actor = _convert(TrainEngineConfig, run.get("actor"), f"{where}: actor") if run else None
        numbered = _CHECKPOINT_DIR.match(checkpoint.name) if checkpoint else None
        step = int(numbered.group(1)) if numbered else (0 if self.checkpoint == INITIAL and run_dir else None)
        if self.output:
            output = Path(self.output)
        else:
            # Without run_dir the model is in the name; with it, model.path only says where the base moved.
            defaults = EvalConfig(model=EvalModelConfig(path=self.model.path))
            default_settings = defaults.result_settings(*defaults._with_run_defaults(run, run_task, where))
            changed = {k: v for k, v in self.result_settings(task, max_new, stops, agent).items()
                       if default_settings.get(k, _UNSET) != v}
            stem = checkpoint.name if checkpoint else INITIAL if run_dir else Path(model_path).name
            name = f"{task_label(task, self.split)}-{stem}{f'-{_digest(changed)}' if changed else ''}.json"
            output = (run_dir if run_dir else Path("runs")) / "eval" / name
        return EvalPlan(run_dir=run_dir, checkpoint=checkpoint, step=step, model_path=model_path, actor=actor,
                        task=task, verifier=verifier, max_new_tokens=max_new, stop_strings=stops, output=output,
                        task_from_run=run_task is not None and _same_data(task, run_task), agent=agent)

    def _with_run_defaults(self, run: dict | None, run_task: TaskConfig | None,
                           where: str) -> tuple[TaskConfig, int, list[str], AgentConfig | None]:
        """The task, response budget, stop strings and agent: each as given, else the run's, else the default."""
        run_rollout = (run or {}).get("rollout", {})
        task = self.task or run_task or TaskConfig()
        max_new = self.max_new_tokens or run_rollout.get("max_new_tokens") or 256
        stops = self.stop_strings if self.stop_strings is not None else list(run_rollout.get("stop_strings", []))
        agent = None if self.single_turn else _agent(run_rollout.get("agent"), self.rollout.agent, where)
        return task, max_new, stops, agent

    def result_settings(self, task: TaskConfig, max_new_tokens: int, stop_strings: list[str],
                        agent: AgentConfig | None) -> dict[str, Any]:
        """Every setting that changes what an evaluation measures, with the run's values filled in
        (the task, sampling, the response budget, the agent, the engine and its batch size, which
        decides each call's sampling seed); not where it runs or how it reports progress."""
        settings: dict[str, Any] = {
            "task": to_plain(task), "split": self.split, "limit": self.limit, "greedy": self.greedy,
            "samples": self.samples, "max_new_tokens": max_new_tokens, "stop_strings": list(stop_strings),
            "agent": to_plain(agent), "model.rollout_dtype": self.model.rollout_dtype,
            "rollout.engine": self.rollout.engine, "rollout.engine_options": to_plain(self.rollout.engine_options),
            "rollout.max_batch_size": self.rollout.max_batch_size}
        if self.samples:  # with greedy decoding only, these change nothing
            settings.update(k=self.ks, temperature=self.temperature, top_p=self.top_p, top_k=self.top_k,
                            seed=self.seed)
        return settings


@dataclass(kw_only=True)
class EvalPlan:
    """What an EvalConfig resolves to (see `EvalConfig.resolve`)."""

    run_dir: Path | None
    checkpoint: Path | None
    """The checkpoint folder (holding actor/), or None for the plain model."""
    step: int | None
    model_path: str
    actor: TrainEngineConfig | None
    """The run's actor config: the model structure (LoRA) the checkpoint was saved from."""
    task: TaskConfig
    verifier: str
    max_new_tokens: int
    stop_strings: list[str]
    output: Path
    agent: AgentConfig | None = None
    """Multi-turn rollouts with this agent (None: single-turn)."""
    task_from_run: bool = False
    """The task names the run's own data (the run's task, or one differing only in how prompts are
    shaped or scored): only its held-out part is evaluated, e.g. a data file's first task.eval_size
    rows (the run trained on the rest)."""


INITIAL = "initial"
"""``checkpoint=initial``: a run's starting model, untrained."""


def _find_checkpoint(run_dir: str | None, checkpoint: str) -> tuple[Path | None, Path | None]:
    from infinirl.runners.checkpoints import Checkpoints

    given = Path(checkpoint).expanduser()
    if run_dir is None:
        if checkpoint == "latest":
            return None, None  # no run: the plain model
        if checkpoint == INITIAL:
            raise ConfigError(f"checkpoint={INITIAL!r} needs run_dir=<training output_dir>: it evaluates that run's "
                              "starting model in the run's setting")
        if not given.name.endswith(".tmp") and not (given / "actor").is_dir():
            raise ConfigError(f"checkpoint={checkpoint!r} needs run_dir=<training output_dir>, or a path to a "
                              "checkpoint folder (runs/<name>/checkpoints/iter_N, holding actor/)")
        run_root = given.resolve().parent.parent  # <run>/checkpoints/iter_N
        _check_checkpoint(checkpoint, given, [name for _, name in Checkpoints(str(run_root)).completed()])
        return run_root, given
    root = Path(run_dir).expanduser()
    if not root.is_dir():
        raise ConfigError(f"run_dir={run_dir!r} is not a folder; pass a training run's output_dir "
                          "(e.g. runs/grpo_chain_sum)")
    if checkpoint == INITIAL:
        return root, None  # the run's model.path as it was before training
    ckpts = root / "checkpoints"
    done = dict(Checkpoints(str(root)).completed())
    if checkpoint == "latest":
        if not done:
            raise ConfigError(f"checkpoint=latest: run_dir={run_dir!r} has no checkpoints/iter_N folder yet "
                              "(a run saves one every save_every iterations and at its end)")
        chosen = ckpts / done[max(done)]
    elif checkpoint.isdigit():
        chosen = ckpts / done.get(int(checkpoint), f"iter_{int(checkpoint):06d}")
    elif (ckpts / checkpoint).is_dir():
        chosen = ckpts / checkpoint
    else:
        chosen = given
    _check_checkpoint(checkpoint, chosen, list(done.values()))
    return root, chosen


def _check_checkpoint(checkpoint: str, folder: Path, finished: list[str]) -> None:
    """``folder`` is a whole checkpoint: committed (not a ``.tmp`` save in progress or abandoned),
    with actor/ and every file its manifest lists, as resume checks it; else a ConfigError."""
    from infinirl.runners.checkpoints import verify_checkpoint

    others = f"finished checkpoints of {folder.parent}: {', '.join(finished) or 'none'}"
    if folder.name.endswith(".tmp"):
        raise ConfigError(f"checkpoint={checkpoint!r}: {folder} is a save that never finished (a checkpoint is "
                          f"renamed from .tmp only once complete); pick a finished one ({others})")
    if not (folder / "actor").is_dir():
        raise ConfigError(f"checkpoint={checkpoint!r}: {folder} is not a checkpoint folder (no actor/ inside); "
                          f"{others}")
    verify_checkpoint(str(folder), fix=f"evaluate another checkpoint with checkpoint=<iteration> ({others})")


def _read_run_config(run_dir: Path) -> dict:
    path = run_dir / RUN_CONFIG_FILE
    if not path.is_file():
        raise ConfigError(f"run_dir={str(run_dir)!r} has no {RUN_CONFIG_FILE} (the run's resolved config, which "
                          "runs write from now on); run the same `infinirl train` command once more to write it "
                          "(it resumes at its last step), then evaluate")
    try:
        run = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ConfigError(f"run_dir: {path} is not valid JSON ({exc})") from None
    if run.get("runner") not in (None, "reasoning") or not isinstance(run.get("model"), dict):
        raise ConfigError(f"run_dir={str(run_dir)!r} is a {run.get('runner')!r} run; eval reads reasoning runs "
                          "(an LLM with model/actor/task sections)")
    return run


def _convert(cls: type, data: Any, where: str):
    try:
        return to_dataclass(cls, data or {})
    except (ConfigError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _agent(run_agent: dict | None, given: dict | None, where: str) -> AgentConfig | None:
    """The agent of an evaluation: the keys given laid over the run's ``rollout.agent`` (nested
    mappings key by key), so one changed key keeps the rest of the run's agent."""
    run_config = _convert(AgentConfig, run_agent, f"{where}: rollout.agent") if run_agent else None
    if given is None:
        return run_config
    return to_dataclass(AgentConfig, _lay_over(run_agent or {}, given), "rollout.agent")


def _lay_over(base: dict, top: dict) -> dict:
    out = dict(base)
    for key, value in top.items():
        out[key] = _lay_over(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


# What selects a task's problems (and so which of them a run held out), besides its name; the
# other task keys only shape the prompts or the scoring.
_DATA_KEYS = ("source", "config", "eval_size", "eval_seed")


def _same_data(task: TaskConfig, run_task: TaskConfig) -> bool:
    """``task`` names the run's own problems, so only the run's held-out part may be evaluated."""
    def data(t: TaskConfig) -> tuple:
        file = Path(t.name).expanduser()  # a data file named by another path is still the same file
        return tuple(getattr(t, k) for k in _DATA_KEYS) + (file.resolve() if file.is_file() else t.name,)

    return data(task) == data(run_task)


def _digest(settings: dict) -> str:
    """A short name for a set of settings, the same for the same settings on any machine."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:8]


_UNSET = object()
