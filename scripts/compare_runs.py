"""Learning curves of several runs in one figure: one line per run, one panel per metric.

Each run's own ``curves.png`` shows its metrics; comparing seeds or recipes needs them side by side.
Runs are given as ``LABEL=RUN_DIR`` (their ``metrics.jsonl`` is read); each ``--panel`` is a metric
key, optionally with a title (``KEY:TITLE``). ``--target`` draws a dashed line in the first panel
(e.g. the success a demo aims at), ``--start`` adds an iteration-0 point to every run's first panel
(e.g. the SFT policy's held-out success, when the runs skipped their own start evaluation).

    python scripts/compare_runs.py --out curves.png --panel eval/success_rate:"held-out success" \\
        --panel eval/success/button-press-topdown-v3 --start 0.511 --target 0.761 \\
        "seed 0=runs/a" "seed 1=runs/b"
"""

from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from infinirl.runners.curves import Panel, plot_panels  # noqa: E402


def _fail(message: str) -> None:
    sys.exit(f"compare_runs: {message}")


def read_metrics(run_dir: str) -> list[dict]:
    """The run's ``metrics.jsonl`` rows; a one-line exit if there is none."""
    path = os.path.join(run_dir, "metrics.jsonl")
    if not os.path.isfile(path):
        _fail(f"{path} not found: give LABEL=RUN_DIR with a run's output_dir")
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def parse_run(spec: str) -> tuple[str, str]:
    label, sep, run_dir = spec.partition("=")
    if not sep or not label or not run_dir:
        _fail(f"run {spec!r} is not LABEL=RUN_DIR")
    return label, run_dir


def parse_panel(spec: str) -> tuple[str, str]:
    key, _, title = spec.partition(":")
    return key, title or key


def labelled_rows(runs: dict[str, list[dict]], keys: list[str], start: float | None) -> list[dict]:
    """One row per (run, logged step), its metrics renamed ``KEY|LABEL`` so each run draws a line of its own."""
    merged = []
    for label, rows in runs.items():
        if start is not None:
            merged.append({"step": 0, f"{keys[0]}|{label}": start})
        for row in rows:
            if "step" in row:
                merged.append({"step": row["step"], **{f"{k}|{label}": row[k] for k in keys if k in row}})
    return merged


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    parser.add_argument("--panel", action="append", required=True, help="a metric key, or KEY:TITLE")
    parser.add_argument("--out", required=True, help="the PNG to write")
    parser.add_argument("--title", default="")
    parser.add_argument("--target", type=float, default=None, help="a dashed line in the first panel")
    parser.add_argument("--start", type=float, default=None, help="an iteration-0 point in the first panel")
    args = parser.parse_args(argv)
    runs = dict(parse_run(spec) for spec in args.runs)
    panels = [parse_panel(spec) for spec in args.panel]
    keys = [key for key, _ in panels]
    metrics = {label: read_metrics(run) for label, run in runs.items()}
    never = [key for key in keys if not any(key in row for rows in metrics.values() for row in rows)]
    if never:
        _fail(f"none of the runs logged {never}: a panel is a key of their metrics.jsonl")
    rows = labelled_rows(metrics, keys, args.start)
    figure = [Panel(title=title, y=tuple(f"{key}|{label}" for label in runs), legend=tuple(runs),
                    target=args.target if i == 0 else None) for i, (key, title) in enumerate(panels)]
    path = plot_panels(rows, figure, args.out, args.title)
    print(path)
    return path


if __name__ == "__main__":
    main()
