"""The macro flows. Each runner registers its name, its typed config and its entry point.

``infinirl train <config>`` reads the config's ``runner:`` key and dispatches through this
registry, so a new flow is one new module with one ``@register_runner`` and no edit elsewhere.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

from infinirl.registry import Registry


@dataclass(frozen=True)
class RunnerSpec:
    name: str
    config_cls: type
    run: Callable
    summary: str
    preflight: Callable | None = None
    """``preflight(cfg)``: the runner's driver-side checks that need no cluster (the env task and its
    options, the policy's options, data files, prompt lengths); raises ConfigError. ``infinirl
    validate`` runs it; the runner's ``run`` runs the same function before any worker starts and
    uses what it returns, so ``train`` refuses exactly what ``validate`` does."""


RUNNERS: Registry[RunnerSpec] = Registry("runner", entry_point_group="infinirl.runners")

# Modules that define runners; imported lazily so `infinirl --help` stays fast.
_RUNNER_MODULES = ("infinirl.runners.runtime_demo", "infinirl.runners.reasoning", "infinirl.runners.embodied",
                  "infinirl.evaluation.runner", "infinirl.runners.sac", "infinirl.runners.sft",
                  "infinirl.runners.realworld_sac", "infinirl.runners.hg_dagger")


def register_runner(name: str, config_cls: type, summary: str, preflight: Callable | None = None):
    def wrap(fn: Callable) -> Callable:
        RUNNERS.add(name, RunnerSpec(name, config_cls, fn, summary, preflight))
        return fn

    return wrap


def load_runners() -> Registry[RunnerSpec]:
    for module in _RUNNER_MODULES:
        importlib.import_module(module)
    return RUNNERS
