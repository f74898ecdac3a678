"""Metrics sinks: JSONL always, TensorBoard by default, W&B (offline) and SwanLab (local) on request."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence

KNOWN_LOGGERS = ("tensorboard", "wandb", "swanlab")


class MetricsLogger:
    def __init__(self, output_dir: str, loggers: Sequence[str], config: dict, run_name: str = "run",
                 start_step: int = 0):
        os.makedirs(output_dir, exist_ok=True)
        self.path = os.path.join(output_dir, "metrics.jsonl")
        self._keep_rows_up_to(start_step)
        self._jsonl = open(self.path, "a")
        self._sinks = []
        for name in loggers:
            if name == "tensorboard":
                from torch.utils.tensorboard import SummaryWriter

                writer = SummaryWriter(os.path.join(output_dir, "tensorboard"))
                self._sinks.append(lambda m, s, w=writer: [w.add_scalar(k, v, s) for k, v in m.items()] and w.flush())
                self._close_tb = writer.close
            elif name == "wandb":
                import wandb

                run = wandb.init(project="infinirl", name=run_name, dir=output_dir, mode="offline", config=config)
                self._sinks.append(lambda m, s, r=run: r.log(m, step=s))
            elif name == "swanlab":
                import swanlab

                swanlab.init(project="infinirl", experiment_name=run_name, logdir=output_dir, mode="local", config=config)
                self._sinks.append(lambda m, s: swanlab.log(m, step=s))
            else:
                raise ValueError(f"unknown logger '{name}'; choose from {', '.join(KNOWN_LOGGERS)}")

    def _keep_rows_up_to(self, step: int) -> None:
        """A fresh run starts an empty file; a resumed one drops rows logged after its checkpoint."""
        rows = read_metrics(self.path) if os.path.exists(self.path) and step > 0 else []
        tmp = self.path + ".tmp"
        with open(tmp, "w") as handle:
            for row in rows:
                if row.get("step", 0) <= step:
                    handle.write(json.dumps(row) + "\n")
        os.replace(tmp, self.path)

    def log(self, metrics: dict, step: int) -> None:
        scalars = {k: float(v) for k, v in metrics.items() if isinstance(v, (int, float))}
        self._jsonl.write(json.dumps({"step": step, **scalars}) + "\n")
        self._jsonl.flush()
        for sink in self._sinks:
            sink(scalars, step)

    def close(self) -> None:
        self._jsonl.close()
        if hasattr(self, "_close_tb"):
            self._close_tb()


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
