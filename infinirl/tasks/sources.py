"""Where a reasoning task's problems come from, by ``task.source``: a registry, so the trainer and
``infinirl eval`` read problems the same way and a new source is one registered entry.

Each source gives the trainer its held-out set and an endless, resumable training stream
(disjoint from the held-out set by construction), and gives the evaluator the problems of a split.
Bad input (an unknown generator, a missing or empty file, rows without the configured keys) is a
``ConfigError`` naming the task key and the fix, raised in the driver before any worker starts.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from infinirl.config import ConfigError
from infinirl.registry import Registry
from infinirl.tasks.config import TaskConfig
from infinirl.tasks.problem import Problem

__all__ = ["TASK_SOURCES", "TaskSource", "answer_format_for", "check_few_shot", "eval_problems", "held_out_size",
           "task_files", "task_label",
           "training_problems", "verifier_for"]


@dataclass(frozen=True, kw_only=True)
class TaskSource:
    training: Callable[[TaskConfig, int], tuple[Any, list[Problem]]]
    """``(task, seed) -> (train stream, held-out problems)``."""
    evaluation: Callable[[TaskConfig, str, int | None, bool], list[Problem]]
    """``(task, split, limit, from_run) -> problems``; ``from_run``: the task is a training run's,
    so only its held-out part is evaluated."""
    verifier: Callable[[TaskConfig, str], str]
    """``(task, split) -> the verifier to score with``, after cheap checks of the task's files."""
    label: Callable[[TaskConfig, str], str]
    """A short name for result files."""
    answer_format: Callable[[TaskConfig], str | None] = lambda task: None
    """The answer extractor matching the format the source's prompts ask for (``marker`` for
    ``####``, ``boxed``, ``tagged``), which ``task.format_bonus`` rewards; None: no particular one
    (a reasoning-gym question carries its own instruction)."""
    files: Callable[[TaskConfig], dict[str, str]] = lambda task: {}
    """``label -> path`` of the files the task's problems are read from (recorded with a training
    run's checkpoints and compared on resume); a generator reads none."""


TASK_SOURCES: Registry[TaskSource] = Registry("task source", entry_point_group="infinirl.task_sources")


def training_problems(task: TaskConfig, seed: int):
    """``(train stream, held-out problems)`` of ``task``; ConfigError naming the task on bad input,
    or naming ``task.few_shot`` when a worked example shows a held-out question."""
    stream, held_out = _guarded(task, lambda: TASK_SOURCES.get(task.source).training(task, seed))
    check_few_shot(task, held_out)
    return stream, held_out


def eval_problems(task: TaskConfig, split: str, limit: int | None, from_run: bool = False) -> list[Problem]:
    problems = _guarded(task, lambda: TASK_SOURCES.get(task.source).evaluation(task, split, limit, from_run))
    check_few_shot(task, problems)
    return problems


def check_few_shot(task: TaskConfig, held_out: list[Problem]) -> None:
    """ConfigError naming ``task.few_shot[i]`` when that worked example's user turn holds the text of
    a held-out question: the model would be shown the problem it is evaluated on, solved."""
    from infinirl.tasks.problem import normalize_question

    if not task.few_shot:
        return
    questions = {normalize_question(str(problem.metadata.get("question", problem.prompt))) for problem in held_out}
    questions.discard("")
    for i, example in enumerate(task.few_shot):
        shown = normalize_question(str(example.get("user", "")))
        for question in questions:
            if question in shown:
                raise ConfigError(f"task.few_shot[{i}] shows the question {question[:80]!r}, which is held out for "
                                  "evaluation; pick a worked example outside the held-out (evaluated) problems")


def verifier_for(task: TaskConfig, split: str) -> str:
    return TASK_SOURCES.get(task.source).verifier(task, split)


def answer_format_for(task: TaskConfig) -> str | None:
    """``task.answer_format`` when set, else the task source's."""
    return task.answer_format or TASK_SOURCES.get(task.source).answer_format(task)


def task_label(task: TaskConfig, split: str) -> str:
    return TASK_SOURCES.get(task.source).label(task, split)


def task_files(task: TaskConfig) -> dict[str, str]:
    return TASK_SOURCES.get(task.source).files(task)


def _guarded(task: TaskConfig, build: Callable):
    try:
        return build()
    except ConfigError:
        raise
    except (KeyError, ValueError, TypeError, FileNotFoundError, OSError) as exc:
        message = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
        raise ConfigError(f"task (source={task.source}, name={task.name!r}): {message}") from None


# --------------------------------------------------------------------------- reasoning-gym generators
def _gym_training(task: TaskConfig, seed: int):
    from infinirl.tasks.reasoning_gym_tasks import ReasoningGymStream, ReasoningGymTask, build_eval_set

    generator = ReasoningGymTask(task.name, task.config, verifier=task.verifier)
    held_out = build_eval_set(generator, task.eval_size, seed=task.eval_seed)
    return ReasoningGymStream(generator, seed=seed, exclude=held_out), held_out


def _gym_evaluation(task: TaskConfig, split: str, limit: int | None, from_run: bool) -> list[Problem]:
    from infinirl.tasks.reasoning_gym_tasks import ReasoningGymTask, build_eval_set

    # The same held-out set a training run evaluated on (same task config and eval seed); past its
    # eval_size the sequence goes on into questions the run may have trained on.
    size = held_out_size(task, limit) if from_run else (limit or task.eval_size)
    return build_eval_set(ReasoningGymTask(task.name, task.config, verifier=task.verifier), size,
                          seed=task.eval_seed)


def held_out_size(task: TaskConfig, limit: int | None) -> int:
    """How many of a run's own problems to evaluate: at most the ``task.eval_size`` it held out."""
    if limit and limit > task.eval_size:
        print(f"eval: limit={limit} is capped at the run's task.eval_size={task.eval_size}: only its held-out "
              "problems are evaluated, the run trained on the others", flush=True)
    return min(limit or task.eval_size, task.eval_size)


TASK_SOURCES.add("reasoning_gym", TaskSource(training=_gym_training, evaluation=_gym_evaluation,
                                             verifier=lambda task, split: task.verifier,
                                             label=lambda task, split: task.name))


# --------------------------------------------------------------------------- datasets: presets and files
def _dataset_training(task: TaskConfig, seed: int):
    from infinirl.tasks.datasets import DATASET_PRESETS, EpochBatchIterator, load_preset

    verifier = _dataset_verifier(task, "train")
    if task.name in DATASET_PRESETS:
        held_out = load_preset(task.name, "test", limit=task.eval_size, verifier=verifier)
        training = load_preset(task.name, "train", verifier=verifier)
        return EpochBatchIterator(_excluding(training, held_out), seed=seed), held_out
    rows = _file_problems(task, verifier, limit=None)
    held_out = _distinct(rows[: task.eval_size])
    training = _excluding(rows[task.eval_size:], held_out)
    if not training:
        raise ConfigError(f"task.name={task.name!r} has {len(rows)} rows and task.eval_size={task.eval_size} of them "
                          "are held out (with the later rows asking the same questions), which leaves none to train "
                          "on; lower task.eval_size or add rows")
    return EpochBatchIterator(training, seed=seed), held_out


def _excluding(problems: list[Problem], held_out: list[Problem]) -> list[Problem]:
    """``problems`` without those asking a held-out question (compared as `normalize_question` does)."""
    from infinirl.tasks.problem import normalize_question

    def question(problem: Problem) -> str:
        return normalize_question(str(problem.metadata.get("question", problem.prompt)))

    excluded = {question(problem) for problem in held_out}
    return [problem for problem in problems if question(problem) not in excluded]


def _dataset_evaluation(task: TaskConfig, split: str, limit: int | None, from_run: bool) -> list[Problem]:
    from infinirl.tasks.datasets import DATASET_PRESETS, load_preset

    verifier = _dataset_verifier(task, split)
    if task.name in DATASET_PRESETS:
        return load_preset(task.name, split, limit=limit, verifier=verifier)
    if from_run:  # the run trained on all but the first eval_size rows, held out once per question
        return _distinct(_file_problems(task, verifier, held_out_size(task, limit)))
    return _file_problems(task, verifier, limit)


def _distinct(problems: list[Problem]) -> list[Problem]:
    """``problems`` with each question (compared as `normalize_question` does) only at its first row,
    as `build_eval_set` draws a generator's: a repeated row would weigh its question twice."""
    from infinirl.tasks.problem import normalize_question

    seen: set[str] = set()
    kept = []
    for problem in problems:
        key = normalize_question(str(problem.metadata.get("question", problem.prompt)))
        if key not in seen:
            seen.add(key)
            kept.append(problem)
    return kept


def _file_problems(task: TaskConfig, verifier: str, limit: int | None) -> list[Problem]:
    from infinirl.tasks.datasets import load_problems

    problems = load_problems(task.name, prompt_key=task.prompt_key, answer_key=task.answer_key, verifier=verifier,
                             limit=limit)
    if not problems:
        raise ConfigError(f"task.name={task.name!r} has no rows; pass a file with one problem per row")
    return problems


def _dataset_verifier(task: TaskConfig, split: str) -> str:
    """Cheap checks of a dataset task's file; the verifier to score with."""
    from infinirl.tasks.datasets import DATASET_PRESETS, ROW_READERS, preset_path

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
        raise ConfigError(f"task.name={task.name!r} is neither a dataset preset ({', '.join(DATASET_PRESETS.names())})"
                          " nor a data file; pass a preset or a .jsonl/.parquet path")
    if path.suffix not in ROW_READERS:
        raise ConfigError(f"task.name={task.name!r}: unsupported file type {path.suffix!r}; "
                          f"supported: {', '.join(ROW_READERS.names())}")
    if task.verifier == "reasoning_gym":
        raise ConfigError("task.verifier=reasoning_gym cannot score rows of a data file; set task.verifier to "
                          "math, gsm8k or a `package.module:function`")
    return task.verifier


def _dataset_answer_format(task: TaskConfig) -> str:
    from infinirl.tasks.datasets import DATASET_PRESETS

    # A data file's rows are asked for the answer after '####' (datasets.NUMBER_ANSWER_TEMPLATE).
    return DATASET_PRESETS.get(task.name).answer_format if task.name in DATASET_PRESETS else "marker"


def _dataset_label(task: TaskConfig, split: str) -> str:
    from infinirl.tasks.datasets import DATASET_PRESETS

    return f"{task.name}-{split}" if task.name in DATASET_PRESETS else Path(task.name).stem


def _dataset_files(task: TaskConfig) -> dict[str, str]:
    from infinirl.tasks.datasets import DATASET_PRESETS, preset_path

    if task.name in DATASET_PRESETS:  # under $INFINIRL_DATA_DIR: which folder it names decides the rows
        return {f"task.name={task.name} ({split} split)": str(preset_path(task.name, split))
                for split in DATASET_PRESETS.get(task.name).splits}
    return {"task.name": str(Path(task.name).expanduser())}


TASK_SOURCES.add("dataset", TaskSource(training=_dataset_training, evaluation=_dataset_evaluation,
                                       verifier=_dataset_verifier, label=_dataset_label, files=_dataset_files,
                                       answer_format=_dataset_answer_format))
