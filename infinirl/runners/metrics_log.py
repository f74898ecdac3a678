"""Metrics sinks: JSONL always, TensorBoard by default, W&B and SwanLab on request (no network).

Every run also gets ``config.json`` (the resolved config it was started with) next to its
metrics, so tools that come later (``infinirl eval run_dir=...``) can rebuild the model exactly.

W&B runs offline (``<output_dir>/wandb/offline-run-*``; upload later with ``wandb sync``) and
SwanLab locally (``<output_dir>/swanlab/run-*``; ``swanlab watch`` needs the dashboard package,
without it the run is recorded offline for ``swanlab sync``). ``WANDB_MODE`` / ``SWANLAB_MODE``
in the environment choose another mode (e.g. ``online``) without a code change.
"""

from __future__ import annotations

import importlib.util
import json
import numbers
import os
from collections.abc import Callable, Sequence

from infinirl.utils import atomic_open, write_json_atomic

KNOWN_LOGGERS = ("tensorboard", "wandb", "swanlab")
CONFIG_FILE = "config.json"


class MetricsLogger:
    def __init__(self, output_dir: str, loggers: Sequence[str], config: dict, run_name: str | None = None,
                 start_step: int = 0):
        for name in loggers:  # before creating anything, so a typo leaves no half-made run behind
            if name not in KNOWN_LOGGERS:
                raise ValueError(f"unknown logger '{name}'; choose from {', '.join(KNOWN_LOGGERS)}")
        os.makedirs(output_dir, exist_ok=True)
        run_name = run_name or os.path.basename(os.path.abspath(output_dir))
        write_json_atomic(os.path.join(output_dir, CONFIG_FILE), config)
        self.path = os.path.join(output_dir, "metrics.jsonl")
        self._keep_rows_up_to(start_step)
        self._jsonl = open(self.path, "a")
        self._sinks: list[Callable[[dict, int], None]] = []
        self._closers: list[Callable[[], None]] = []
        for name in loggers:
            _require(name)
            if name == "tensorboard":
                from torch.utils.tensorboard import SummaryWriter

                writer = SummaryWriter(os.path.join(output_dir, "tensorboard"))

                def tb_log(metrics: dict, step: int, w=writer) -> None:
                    for key, value in metrics.items():
                        w.add_scalar(key, value, step)
                    w.flush()

                self._sinks.append(tb_log)
                self._closers.append(writer.close)
            elif name == "wandb":
                import wandb

                run = wandb.init(project="infinirl", name=run_name, dir=output_dir, config=config,
                                 mode=os.environ.get("WANDB_MODE", "offline"))
                self._sinks.append(lambda m, s, r=run: r.log(m, step=s))
                self._closers.append(run.finish)
            else:  # swanlab
                import swanlab

                default_mode = "local" if importlib.util.find_spec("swanboard") else "offline"
                run = swanlab.init(project="infinirl", experiment_name=run_name, config=config,
                                   logdir=os.path.join(output_dir, "swanlab"),
                                   mode=os.environ.get("SWANLAB_MODE", default_mode))
                self._sinks.append(lambda m, s, r=run: r.log(m, step=s))
                self._closers.append(run.finish)

    def _keep_rows_up_to(self, step: int) -> None:
        """A fresh run starts an empty file; a resumed one drops rows logged after its checkpoint."""
        rows = read_metrics(self.path) if os.path.exists(self.path) and step > 0 else []
        with atomic_open(self.path, "w") as handle:
            for row in rows:
                if row.get("step", 0) <= step:
                    handle.write(json.dumps(row) + "\n")

    def log(self, metrics: dict, step: int) -> None:
        """Log the scalar entries of ``metrics`` (Python, NumPy or one-element tensor numbers)."""
        scalars = {k: s for k, s in ((k, _scalar(v)) for k, v in metrics.items()) if s is not None}
        self._jsonl.write(json.dumps({"step": step, **scalars}) + "\n")
        self._jsonl.flush()
        for sink in self._sinks:
            sink(scalars, step)

    def close(self) -> None:
        """Flush and close every sink (W&B and SwanLab write their run files on finish). Idempotent."""
        if not self._jsonl.closed:
            self._jsonl.close()
        closers, self._closers = self._closers, []
        for close in closers:
            close()


def _require(logger: str) -> None:
    if logger != "tensorboard" and importlib.util.find_spec(logger) is None:
        raise ImportError(f"logger '{logger}' needs the {logger} package: pip install 'infinirl[loggers]'")


def _scalar(value) -> float | None:
    if isinstance(value, numbers.Real):  # bool, int, float and NumPy scalars
        return float(value)
    if getattr(value, "numel", None) is not None and value.numel() == 1:  # a one-element tensor
        return float(value.item())
    return None


def read_metrics(path: str) -> list[dict]:
    with open(path) as handle:
        return [json.loads(line) for line in handle if line.strip()]


def plot_curves(rows: list[dict], keys: Sequence[str], path: str, title: str) -> str | None:
    """One PNG with a panel per metric (skips metrics never logged)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    present = [k for k in keys if any(k in r for r in rows)]
    if not present:
        return None
    fig, axes = plt.subplots(1, len(present), figsize=(5 * len(present), 3.5), squeeze=False)
    for ax, key in zip(axes[0], present):
        points = [(r["step"], r[key]) for r in rows if key in r]
        ax.plot([p[0] for p in points], [p[1] for p in points], marker="o", markersize=3)
        ax.set_title(key)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
