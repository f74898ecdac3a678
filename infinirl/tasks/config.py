"""The ``task`` section shared by the reasoning runner and ``infinirl eval``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from infinirl.config import ConfigError, bounded

__all__ = ["TaskConfig"]


@dataclass(kw_only=True)
class TaskConfig:
    source: str = "reasoning_gym"
    """Where problems come from, by registered task source: reasoning_gym (a generator) | dataset
    (a preset such as gsm8k / math500, or a JSONL/Parquet file)."""
    name: str = "chain_sum"
    """reasoning-gym task name, or dataset preset (gsm8k, math500) / JSONL/Parquet path."""
    config: dict[str, Any] = field(default_factory=lambda: {"min_terms": 2, "max_terms": 2, "min_digits": 1,
                                                            "max_digits": 2})
    """Generator options of the reasoning-gym task."""
    verifier: str = "reasoning_gym"
    """Reward verifier: reasoning_gym | math | gsm8k | a dotted path `pkg.module:function`."""
    format_bonus: float = 0.0
    """Added to the reward of a response giving an answer in ``answer_format`` (0: off)."""
    answer_format: str | None = None
    """The answer extractor the format bonus checks: marker (``####``) | boxed | tagged (``<answer>``);
    default: the task source's (a dataset preset's or data file's prompt instruction, ``tagged`` for
    fictional_kb; none for reasoning-gym and code, where a format bonus needs it set)."""
    eval_size: int = bounded(64, ge=0)
    """Held-out problems, excluded from training by question text (a data file: its first rows, each
    question once)."""
    eval_seed: int = bounded(1_000_003, ge=0)
    """Seeds the held-out problems a generator draws (reasoning_gym)."""
    system_prompt: str | None = None
    few_shot: list[dict[str, str]] = field(default_factory=list)
    """Worked examples shown before every question as earlier chat turns, each
    ``{user: ..., assistant: ...}`` (e.g. how to call a tool, for a model too small to follow a
    description of it). An example showing a held-out question is refused (`sources.check_few_shot`)."""
    prompt_key: str = "question"
    answer_key: str = "answer"

    def instructions(self) -> str:
        """What every prompt tells the model besides its question: the system prompt and the worked
        examples, joined (what an agent environment checks for the tools it offers)."""
        examples = [text for example in self.few_shot for text in example.values()]
        return "\n".join([self.system_prompt or "", *examples])

    def validate(self) -> None:
        from infinirl.tasks.sources import TASK_SOURCES
        from infinirl.tasks.verifiers import check_verifier

        for i, example in enumerate(self.few_shot):
            if set(example) != {"user", "assistant"} or not all(isinstance(v, str) for v in example.values()):
                raise ConfigError(f"task.few_shot[{i}] must be {{user: <text>, assistant: <text>}}, got {example!r}")
        if self.source not in TASK_SOURCES:
            raise ConfigError(f"task.source={self.source!r} is not registered; registered: "
                              f"{', '.join(TASK_SOURCES.names())}")
        try:
            check_verifier(self.verifier)
        except (ValueError, ImportError, AttributeError, TypeError, KeyError) as exc:
            raise ConfigError(f"task.verifier={self.verifier!r}: {exc}") from None
        self._validate_answer_format()

    def _validate_answer_format(self) -> None:
        from infinirl.tasks.answers import ANSWER_EXTRACTORS
        from infinirl.tasks.sources import answer_format_for

        if self.answer_format is not None and self.answer_format not in ANSWER_EXTRACTORS:
            raise ConfigError(f"task.answer_format={self.answer_format!r} is not an answer extractor; use one of "
                              f"{', '.join(ANSWER_EXTRACTORS.names())}")
        if self.format_bonus and answer_format_for(self) is None:
            raise ConfigError(f"task.format_bonus={self.format_bonus} needs task.answer_format: task.source="
                              f"{self.source} asks for no particular answer format; set it to marker, boxed or tagged")
