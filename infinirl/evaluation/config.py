"""Typed configuration of `infinirl eval`, and what it resolves to before anything starts.

Two ways to name the model: a Hugging Face folder (``model.path``), or a training run
(``run_dir``) whose checkpoint is loaded into an actor built with that run's own actor config
(LoRA, dtypes: read from the ``config.json`` every run writes) and synced into the rollout
engine, exactly as during training. `EvalConfig.resolve` reads the run folder and checks every
path, so a missing run, checkpoint or dataset is a `ConfigError` naming its key, before Ray starts.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from infinirl.config import ConfigError, to_dataclass
from infinirl.engines.train_base import TrainEngineConfig
from infinirl.runners.reasoning_config import TaskConfig
from infinirl.runtime import ClusterConfig

RUN_CONFIG_FILE = "config.json"  # written next to metrics.jsonl by runners.metrics_log.MetricsLogger
_STEP_DIR = re.compile(r"^step_(\d+)$")


@dataclass
class EvalModelConfig:
    path: str | None = None
    """Local HF model folder or the embedded `smollm2-135m-instruct`. None: the run's base model
    (with run_dir), else the embedded default. With run_dir, set it only if the base model moved."""
    rollout_dtype: str = "float32"
    """Inference dtype of the rollout engine."""


@dataclass
class EvalRolloutConfig:
    engine: str = "hf"
    """Inference engine by registered name: hf | vllm (optional extra)."""
    engine_options: dict[str, Any] = field(default_factory=dict)
    max_batch_size: int = 64
    """Sequences decoded together per rollout rank; one call carries max_batch_size // n prompts."""


@dataclass
class EvalConfig:
    runner: str = "eval"
    run_dir: str | None = None
    """A training run's output_dir: evaluate its checkpoint (None: evaluate model.path as is)."""
    checkpoint: str = "latest"
    """With run_dir: latest | a step number (40) | a folder name (step_000040) | a checkpoint path."""
    model: EvalModelConfig = field(default_factory=EvalModelConfig)
    task: TaskConfig | None = None
    """Problems and verifier (same keys as training). None: the run's task (its held-out set)
    with run_dir, else the default reasoning-gym chain_sum task. Setting any task key replaces the
    whole task, e.g. task.source=dataset task.name=gsm8k."""
    split: str = "test"
    """Split of a dataset preset (gsm8k: train|test)."""
    limit: int | None = None
    """Evaluate only the first N problems (None: the whole dataset; reasoning-gym tasks draw
    task.eval_size problems)."""
    samples: int = 4
    """Sampled responses per problem for pass@k (0: greedy only)."""
    k: int | list[int] = field(default_factory=lambda: [1, 4])
    """pass@k values to report, each <= samples (unbiased estimator over the samples)."""
    greedy: bool = True
    """Also decode one greedy response per problem: greedy accuracy."""
    temperature: float = 1.0
    top_p: float = 1.0
    top_k: int = 0
    max_new_tokens: int | None = None
    """Response cap. None: the run's rollout.max_new_tokens with run_dir, else 256."""
    stop_strings: list[str] | None = None
    """None: the run's rollout.stop_strings with run_dir, else none."""
    seed: int = 0
    """Sampling seed: the same config gives the same samples whatever the number of rollout ranks."""
    output: str | None = None
    """Results JSON. None: <run_dir>/eval/<task>-step_<N>.json, or runs/eval/<task>-<model>.json."""
    per_problem: bool = True
    """Write each problem's counts, greedy correctness and greedy response into the results."""
    progress: bool = True
    """tqdm progress bar over generated sequences."""
    num_threads: int = 0
    """torch threads per worker (0 = torch default)."""
    rollout: EvalRolloutConfig = field(default_factory=EvalRolloutConfig)
    placement: dict[str, str] = field(default_factory=lambda: {"actor": "0", "rollout": "0", "reward": "0"})
    """actor (only with run_dir: loads the checkpoint, then exits), rollout (data parallel) and reward."""
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    @property
    def ks(self) -> list[int]:
        return [self.k] if isinstance(self.k, int) else list(self.k)

    def validate(self) -> None:
        from infinirl.engines.registry import ROLLOUT_ENGINES
        from infinirl.runtime.placement import PlacementError, parse_spec

        if self.samples < 0:
            raise ConfigError(f"samples={self.samples} must be >= 0")
        if not self.samples and not self.greedy:
            raise ConfigError("samples=0 and greedy=false: nothing to evaluate; set samples>0 or greedy=true")
        for k in self.ks:
            if k < 1:
                raise ConfigError(f"k={k}: every k must be >= 1")
            if k > self.samples:
                raise ConfigError(f"k={k} is larger than samples={self.samples}: pass@k needs at least k "
                                  f"samples per problem; raise samples or lower k")
        if self.samples and self.temperature <= 0:
            raise ConfigError(f"temperature={self.temperature}: sampled pass@k needs temperature > 0 "
                              "(greedy accuracy comes from greedy=true)")
        if not 0 < self.top_p <= 1 or self.top_k < 0:
            raise ConfigError(f"top_p={self.top_p} must be in (0, 1] and top_k={self.top_k} >= 0")
        for key in ("limit", "max_new_tokens"):
            if getattr(self, key) is not None and getattr(self, key) < 1:
                raise ConfigError(f"{key}={getattr(self, key)} must be >= 1 (or null)")
        if self.rollout.max_batch_size < 1:
            raise ConfigError(f"rollout.max_batch_size={self.rollout.max_batch_size} must be >= 1")
        if self.rollout.engine not in ROLLOUT_ENGINES:
            raise ConfigError(f"rollout.engine={self.rollout.engine!r} is not registered; "
                              f"registered: {', '.join(ROLLOUT_ENGINES.names())}")
        plan = self.resolve()
        needed = {"rollout", "reward"} | ({"actor"} if plan.checkpoint else set())
        missing = needed - set(self.placement)
        if missing:
            raise ConfigError(f"placement must place {', '.join(sorted(needed))}; missing {sorted(missing)}")
        for component, spec in self.placement.items():
            if component not in ("actor", "rollout", "reward"):
                raise ConfigError(f"placement.{component}: eval has no such component; use actor, rollout, reward")
            try:
                parse_spec(spec, component)
            except PlacementError as exc:
                raise ConfigError(f"placement.{component}: {exc}") from None

    def resolve(self) -> EvalPlan:
        """The run, checkpoint, model, task and output this config names; ConfigError if one is missing."""
        run_dir, checkpoint = _find_checkpoint(self.run_dir, self.checkpoint)
        run = _read_run_config(run_dir) if run_dir else None
        model_path = self.model.path or (run["model"]["path"] if run else "smollm2-135m-instruct")
        _check_model_path(model_path, "model.path" if self.model.path or not run else
                          f"model.path (from {run_dir / RUN_CONFIG_FILE})")
        if self.task is not None:
            task = self.task
        elif run is not None:
            task = _convert(TaskConfig, run.get("task"), f"{run_dir / RUN_CONFIG_FILE}: task")
        else:
            task = TaskConfig()
        verifier = _check_task(task, self.split)
        run_rollout = (run or {}).get("rollout", {})
        max_new = self.max_new_tokens or (run_rollout.get("max_new_tokens") if run else None) or 256
        stops = self.stop_strings if self.stop_strings is not None else list(run_rollout.get("stop_strings", []))
        actor = _convert(TrainEngineConfig, run.get("actor"), f"{run_dir / RUN_CONFIG_FILE}: actor") if run else None
        step = int(_STEP_DIR.match(checkpoint.name).group(1)) if checkpoint and _STEP_DIR.match(checkpoint.name) else None
        label = task_label(task, self.split)
        if self.output:
            output = Path(self.output)
        elif run_dir:
            output = run_dir / "eval" / f"{label}-{checkpoint.name}.json"
        else:
            output = Path("runs") / "eval" / f"{label}-{Path(model_path).name}.json"
        return EvalPlan(run_dir, checkpoint, step, model_path, actor, task, verifier, max_new, stops, output,
                        task_from_run=self.task is None and run is not None)


@dataclass
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
    task_from_run: bool = False
    """The task is the run's: a data file then contributes only its held-out rows (the first
    task.eval_size; the run trained on the rest)."""


def task_label(task: TaskConfig, split: str) -> str:
    from infinirl.tasks.datasets import DATASET_PRESETS

    if task.source == "dataset":
        return f"{task.name}-{split}" if task.name in DATASET_PRESETS else Path(task.name).stem
    return task.name


def _find_checkpoint(run_dir: str | None, checkpoint: str) -> tuple[Path | None, Path | None]:
    given = Path(checkpoint).expanduser()
    if run_dir is None:
        if checkpoint == "latest":
            return None, None  # no run: the plain model
        if not (given / "actor").is_dir():
            raise ConfigError(f"checkpoint={checkpoint!r} needs run_dir=<training output_dir>, or a path to a "
                              "checkpoint folder (runs/<name>/checkpoints/step_N, holding actor/)")
        return given.resolve().parent.parent, given  # <run>/checkpoints/step_N
    root = Path(run_dir).expanduser()
    if not root.is_dir():
        raise ConfigError(f"run_dir={run_dir!r} is not a folder; pass a training run's output_dir (e.g. runs/grpo_chain_sum)")
    ckpts = root / "checkpoints"
    done = sorted(d.name for d in ckpts.iterdir() if _STEP_DIR.match(d.name)) if ckpts.is_dir() else []
    if checkpoint == "latest":
        if not done:
            raise ConfigError(f"checkpoint=latest: run_dir={run_dir!r} has no checkpoints/step_N folder yet "
                              "(a run saves one every save_every steps and at its end)")
        chosen = ckpts / done[-1]
    elif checkpoint.isdigit():
        chosen = ckpts / f"step_{int(checkpoint):06d}"
    elif (ckpts / checkpoint).is_dir():
        chosen = ckpts / checkpoint
    else:
        chosen = given
    if not (chosen / "actor").is_dir():
        raise ConfigError(f"checkpoint={checkpoint!r}: {chosen} is not a checkpoint folder (no actor/ inside); "
                          f"checkpoints of {run_dir}: {', '.join(done) or 'none'}")
    return root, chosen


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


def _check_model_path(path: str, key: str) -> None:
    from infinirl.models.hf_causal_lm import EMBEDDED_MODELS

    hub_id = path.count("/") == 1 and not path.startswith((".", "/", "~"))
    if path not in EMBEDDED_MODELS and not hub_id and not Path(path).expanduser().is_dir():
        raise ConfigError(f"{key}={path!r} is not a folder; pass a local Hugging Face model folder or the "
                          f"embedded default ({', '.join(EMBEDDED_MODELS)})")


def _check_task(task: TaskConfig, split: str) -> str:
    """Cheap checks of the task's dataset; returns the verifier to score with."""
    from infinirl.tasks.datasets import DATASET_PRESETS, ROW_READERS, preset_path

    if task.source == "reasoning_gym":
        return task.verifier
    if task.name in DATASET_PRESETS:
        preset = DATASET_PRESETS.get(task.name)
        if split not in preset.splits:
            raise ConfigError(f"split={split!r}: dataset preset {task.name!r} has splits {', '.join(preset.splits)}")
        path = preset_path(task.name, split)
        if not path.is_file():
            raise ConfigError(f"task.name={task.name!r}: the preset's file {path} does not exist; set "
                              "INFINIRL_DATA_DIR to the folder holding gsm8k/ and math500/")
        # reasoning_gym (the TaskConfig default) cannot score dataset rows: presets bring their own.
        return preset.verifier if task.verifier == "reasoning_gym" else task.verifier
    path = Path(task.name).expanduser()
    if not path.is_file():
        raise ConfigError(f"task.name={task.name!r} is neither a dataset preset ({', '.join(DATASET_PRESETS.names())}) "
                          f"nor a data file; pass a preset or a .jsonl/.parquet path")
    if path.suffix not in ROW_READERS:
        raise ConfigError(f"task.name={task.name!r}: unsupported file type {path.suffix!r}; "
                          f"supported: {', '.join(ROW_READERS.names())}")
    if task.verifier == "reasoning_gym":
        raise ConfigError("task.verifier=reasoning_gym cannot score rows of a data file; set task.verifier to "
                          "math, gsm8k or a `package.module:function`")
    return task.verifier
