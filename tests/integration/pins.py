"""The first iterations of every runner, pinned: a change in what a runner learns (an estimator, a
loss, a default, the order data is drawn in) changes these numbers and fails in the default suite,
without running the slow learning tests.

Each runner's end-to-end test (``test_*_pipeline.py``) runs a tiny problem from fixed seeds and
compares the metrics of its straight run with ``pinned_metrics.json``. A deliberate change of
learning behaviour re-pins them: ``INFINIRL_REPIN=1 pytest tests/integration -k "resumes_exactly or
asynchronous"`` rewrites the file (the asynchronous modes are pinned by their own tests), and the
diff of that file shows in review what changed.

Pinned: ``sac``, ``embodied``, ``embodied_async``, ``reasoning``, ``reasoning_async``,
``reasoning_agent``, ``sft``, and the robot runners ``realworld_sac`` and ``hg_dagger``
(``INFINIRL_REPIN=1 pytest tests/integration/realworld -k "pinned or aggregates"``). A simulated
robot in real time is not reproducible: what a step observes depends on where its control thread's
ticks fall between the command and the observation. The robot runners' pinned runs therefore drive
the simulated Sawyer with ``robot.options.lockstep=true`` (one control period per command,
:mod:`infinirl.realworld.sim_robot`), and pin what that makes a function of the seeds (rewards,
losses, success, interventions, dataset size), never timing (late steps, rates, seconds).
``realworld_sac`` is pinned in ``pipeline.mode=sync`` with one turn per iteration: its asynchronous
mode, where the policy version a step acts with depends on the learner's pace, is not. ``hg_dagger``'s
pinned run composes the ``hg_dagger_sawyer_reach`` config, so a change to that file re-pins too.
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
