"""The run's metrics: ``metrics.jsonl`` always, plus the configured sinks (:mod:`.loggers`).

Every run also gets ``config.json`` (the resolved config it runs with) next to its metrics, so
tools that come later (``infinirl eval run_dir=...``) can rebuild the model exactly.
"""

from __future__ import annotations

import json
import numbers
import os
import sys
from collections.abc import Sequence

from infinirl.config import ConfigError
from infinirl.runners.loggers import LOGGERS, Sink, require_logger
from infinirl.utils import atomic_open, write_json_atomic

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"


class MetricsLogger:
    def __init__(self, output_dir: str, loggers: Sequence[str], config: dict, run_name: str | None = None,
                 start_step: int = 0):
        for name in loggers:  # before creating anything, so a typo leaves no half-made run behind
            if name not in LOGGERS:
                raise ValueError(f"unknown logger '{name}'; choose from {', '.join(LOGGERS.names())}")
            require_logger(name)
        os.makedirs(output_dir, exist_ok=True)
        run_name = run_name or os.path.basename(os.path.abspath(output_dir))
        write_json_atomic(os.path.join(output_dir, CONFIG_FILE), config)
        self.path = os.path.join(output_dir, METRICS_FILE)
        self.rows_logged = 0
        self._keep_rows_up_to(start_step)
        self._jsonl = open(self.path, "a")
        self._sinks: list[Sink] = [LOGGERS.get(name)(output_dir, run_name, config, start_step=start_step)
                                   for name in loggers]

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
        self.rows_logged += 1
        for sink in self._sinks:
            sink.log(scalars, step)

    def close(self) -> None:
        """Flush and close every sink (W&B and SwanLab write their run files on finish). Idempotent."""
        if not self._jsonl.closed:
            self._jsonl.close()
        sinks, self._sinks = self._sinks, []
        for sink in sinks:
            sink.close()


def _scalar(value) -> float | None:
    if isinstance(value, numbers.Real):  # bool, int, float and NumPy scalars
        return float(value)
    if getattr(value, "numel", None) is not None and value.numel() == 1:  # a one-element tensor
        return float(value.item())
    return None


def read_metrics(path: str, warn: bool = True) -> list[dict]:
    """The rows of a ``metrics.jsonl``. A last line that is not JSON was cut off when the run was
    killed while logging it: it is dropped (with a warning unless ``warn=False``), as resuming drops
    every row after its checkpoint anyway. A damaged line anywhere else is a ConfigError naming the
    file and line, since the rows after it cannot be trusted either."""
    with open(path, errors="replace") as handle:
        lines = [(number, line) for number, line in enumerate(handle, 1) if line.strip()]
    rows = []
    for index, (number, line) in enumerate(lines):
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            if index == len(lines) - 1:
                if warn:
                    print(f"infinirl: {path} line {number} was cut off mid-write (the run was killed while "
                          "logging); dropping it", file=sys.stderr, flush=True)
                break
            raise ConfigError(f"{path} line {number} is not a JSON row ({exc.msg}); repair or delete that line, "
                              "or start over with resume=false") from None
        if not isinstance(row, dict):
            raise ConfigError(f"{path} line {number} is not a JSON object of metrics; repair or delete that line, "
                              "or start over with resume=false")
        rows.append(row)
    return rows
