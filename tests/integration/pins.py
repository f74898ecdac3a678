"""The first iterations of every runner, pinned: a change in what a runner learns (an estimator, a
loss, a default, the order data is drawn in) changes these numbers and fails in the default suite,
without running the slow learning tests.

Each runner's end-to-end test (``test_*_pipeline.py``) runs a tiny problem from fixed seeds and
compares the metrics of its straight run with ``pinned_metrics.json``. A deliberate change of
learning behaviour re-pins them: ``INFINIRL_REPIN=1 pytest tests/integration -k "resumes_exactly or
asynchronous"`` rewrites the file (the asynchronous modes are pinned by their own tests), and the
diff of that file shows in review what changed.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

PINS = Path(__file__).with_name("pinned_metrics.json")
# Loose enough for float rounding across CPUs and thread counts over a few iterations, tight
# enough that any change to an estimator, loss or data order moves a value past it.
RELATIVE, ABSOLUTE = 2e-3, 1e-5


def check_pinned(runner: str, run_dir: Path, keys: list[str]) -> None:
    """The metrics ``keys`` of every row of ``run_dir/metrics.jsonl`` equal the pins of ``runner``."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    measured = {f"{row['step']}:{key}": row[key] for row in rows for key in keys if key in row}
    pins = json.loads(PINS.read_text()) if PINS.exists() else {}
    if os.environ.get("INFINIRL_REPIN"):
        pins[runner] = measured
        PINS.write_text(json.dumps(pins, indent=2, sort_keys=True) + "\n")
        return
    assert runner in pins, f"no pinned metrics for {runner}: run with INFINIRL_REPIN=1 once"
    assert set(measured) == set(pins[runner]), "the runner logs other metrics than were pinned"
    for key, expected in pins[runner].items():
        assert measured[key] == pytest.approx(expected, rel=RELATIVE, abs=ABSOLUTE), key
