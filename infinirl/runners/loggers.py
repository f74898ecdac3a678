"""Metric sinks by name (``loggers: [tensorboard, wandb, swanlab]``): a registry, so a new sink is
one registered factory and no edit of the metrics logger.

A factory takes ``(output_dir, run_name, config)`` and returns a :class:`Sink`. W&B runs offline
(``<output_dir>/wandb/offline-run-*``; upload later with ``wandb sync``) and SwanLab locally
(``<output_dir>/swanlab/run-*``; without its dashboard package the run is recorded offline for
``swanlab sync``). ``WANDB_MODE`` / ``SWANLAB_MODE`` choose another mode (e.g. ``online``).
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Callable
from dataclasses import dataclass

from infinirl.registry import Registry

__all__ = ["LOGGERS", "Sink", "require_logger"]


@dataclass(frozen=True, kw_only=True)
class Sink:
    log: Callable[[dict, int], None]
    """``log(scalars, step)``."""
    close: Callable[[], None]


LOGGERS: Registry[Callable[[str, str, dict], Sink]] = Registry("logger", entry_point_group="infinirl.loggers")

_PACKAGES = {"wandb": "wandb", "swanlab": "swanlab"}


def require_logger(name: str) -> None:
    """Raise ImportError naming the extra to install when a logger's package is missing."""
    package = _PACKAGES.get(name)
    if package and importlib.util.find_spec(package) is None:
        raise ImportError(f"logger '{name}' needs the {package} package: pip install 'infinirl[loggers]'")


@LOGGERS.register("tensorboard")
def _tensorboard(output_dir: str, run_name: str, config: dict) -> Sink:
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(os.path.join(output_dir, "tensorboard"))

    def log(metrics: dict, step: int) -> None:
        for key, value in metrics.items():
            writer.add_scalar(key, value, step)
        writer.flush()

    return Sink(log=log, close=writer.close)


@LOGGERS.register("wandb")
def _wandb(output_dir: str, run_name: str, config: dict) -> Sink:
    import wandb

    run = wandb.init(project="infinirl", name=run_name, dir=output_dir, config=config,
                     mode=os.environ.get("WANDB_MODE", "offline"))
    return Sink(log=lambda metrics, step: run.log(metrics, step=step), close=run.finish)


@LOGGERS.register("swanlab")
def _swanlab(output_dir: str, run_name: str, config: dict) -> Sink:
    import swanlab

    default_mode = "local" if importlib.util.find_spec("swanboard") else "offline"
    run = swanlab.init(project="infinirl", experiment_name=run_name, config=config,
                       logdir=os.path.join(output_dir, "swanlab"), mode=os.environ.get("SWANLAB_MODE", default_mode))
    return Sink(log=lambda metrics, step: run.log(metrics, step=step), close=run.finish)
