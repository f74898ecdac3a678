"""Metric sinks by name (``loggers: [tensorboard, wandb, swanlab]``): a registry, so a new sink is
one registered factory and no edit of the metrics logger.

A factory takes ``(output_dir, run_name, config, start_step=...)`` and returns a :class:`Sink`;
``start_step`` is the iteration a resumed run continues after (0 for a fresh run). W&B runs offline
(``<output_dir>/wandb/offline-run-*``; upload later with ``wandb sync``) and SwanLab locally
(``<output_dir>/swanlab/run-*``; without its dashboard package the run is recorded offline for
``swanlab sync``). ``WANDB_MODE`` / ``SWANLAB_MODE`` choose another mode (e.g. ``online``).

On resume the sinks continue the run instead of starting a second one beside it: TensorBoard hides
the steps a crashed run logged after the checkpoint (``purge_step``), so they are not shown twice;
W&B and SwanLab keep the run's id in ``<output_dir>/<logger>/run_id`` and reopen that run
(``resume="allow"``). Their steps only move forward, so there the steps a crashed run logged past
the checkpoint stay, and the resumed run's values for those steps are dropped by W&B / SwanLab.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Callable
from dataclasses import dataclass

from infinirl.registry import Registry
from infinirl.utils import write_text_atomic

__all__ = ["LOGGERS", "Sink", "require_logger"]


@dataclass(frozen=True, kw_only=True)
class Sink:
    log: Callable[[dict, int], None]
    """``log(scalars, step)``."""
    close: Callable[[], None]


LOGGERS: Registry[Callable[..., Sink]] = Registry("logger", entry_point_group="infinirl.loggers")

_PACKAGES = {"wandb": "wandb", "swanlab": "swanlab"}


def require_logger(name: str) -> None:
    """Raise ImportError naming the extra to install when a logger's package is missing."""
    package = _PACKAGES.get(name)
    if package and importlib.util.find_spec(package) is None:
        raise ImportError(f"logger '{name}' needs the {package} package: pip install 'infinirl[loggers]'")


RUN_ID_FILE = "run_id"
"""In a logger's folder: the id of the W&B / SwanLab run this output folder logs to."""


@LOGGERS.register("tensorboard")
def _tensorboard(output_dir: str, run_name: str, config: dict, start_step: int = 0) -> Sink:
    from torch.utils.tensorboard import SummaryWriter

    # A resumed run logs again from start_step + 1; what a crashed run wrote there (after its last
    # checkpoint) is purged on reading, so each step shows once, with the resumed run's value.
    writer = SummaryWriter(os.path.join(output_dir, "tensorboard"), purge_step=start_step + 1 if start_step else None)

    def log(metrics: dict, step: int) -> None:
        for key, value in metrics.items():
            writer.add_scalar(key, value, step)
        writer.flush()

    return Sink(log=log, close=writer.close)


@LOGGERS.register("wandb")
def _wandb(output_dir: str, run_name: str, config: dict, start_step: int = 0) -> Sink:
    import wandb

    folder = os.path.join(output_dir, "wandb")
    run = wandb.init(project="infinirl", name=run_name, dir=output_dir, config=config,
                     mode=os.environ.get("WANDB_MODE", "offline"), **_resume_kwargs(folder, start_step))
    _remember_run_id(folder, run.id)
    return Sink(log=lambda metrics, step: run.log(metrics, step=step), close=run.finish)


@LOGGERS.register("swanlab")
def _swanlab(output_dir: str, run_name: str, config: dict, start_step: int = 0) -> Sink:
    import swanlab

    folder = os.path.join(output_dir, "swanlab")
    default_mode = "local" if importlib.util.find_spec("swanboard") else "offline"
    run = swanlab.init(project="infinirl", experiment_name=run_name, config=config, logdir=folder,
                       mode=os.environ.get("SWANLAB_MODE", default_mode), **_resume_kwargs(folder, start_step))
    _remember_run_id(folder, run.id)
    return Sink(log=lambda metrics, step: run.log(metrics, step=step), close=run.finish)


def _resume_kwargs(folder: str, start_step: int) -> dict:
    """``id`` and ``resume`` to continue the run this folder logged to, when resuming a checkpoint.
    A fresh run (start_step 0) gets a new id even if an old one is there: its records were set aside."""
    path = os.path.join(folder, RUN_ID_FILE)
    if start_step <= 0 or not os.path.isfile(path):
        return {}
    with open(path) as handle:
        run_id = handle.read().strip()
    return {"id": run_id, "resume": "allow"} if run_id else {}


def _remember_run_id(folder: str, run_id: str) -> None:
    os.makedirs(folder, exist_ok=True)
    write_text_atomic(os.path.join(folder, RUN_ID_FILE), f"{run_id}\n")
