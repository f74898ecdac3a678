"""Per-task success of a held-out evaluation, shared by the simulator runners' evaluators."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["task_success_metrics"]


def task_success_metrics(successes: Sequence[bool], tasks: Sequence[str | None]) -> dict[str, float]:
    """``eval/success/<task>`` and ``eval/episodes/<task>`` for each task of the episodes (in order of
    first appearance), where they ran more than one task; ``{}`` otherwise (a single task's success
    is ``eval/success_rate`` already)."""
    named = [task for task in tasks if task is not None]
    if len(set(named)) < 2:
        return {}
    metrics: dict[str, float] = {}
    for task in dict.fromkeys(named):
        done = [success for success, name in zip(successes, tasks, strict=True) if name == task]
        metrics[f"eval/success/{task}"] = float(np.mean(done))
        metrics[f"eval/episodes/{task}"] = len(done)
    return metrics
