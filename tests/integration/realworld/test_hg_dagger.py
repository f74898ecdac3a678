"""HG-DAgger end to end through the command line as a user runs it (own process, own Ray): a
simulated human takes over the simulated Sawyer (MetaWorld reach, real time) when the policy drifts;
its steps are stored with their flag and aggregated, and the policy is cloned on them each iteration."""

import importlib.util
import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None, reason="needs metaworld")


def train(output_dir, *overrides, timeout=600):
    proc = subprocess.run([sys.executable, "-m", "infinirl.cli", "train", "hg_dagger_sawyer_reach",
                           f"output_dir={output_dir}", "loggers=[]", "cluster.log_to_driver=false", *overrides],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return [json.loads(line) for line in (output_dir / "metrics.jsonl").read_text().splitlines()]


def test_hg_dagger_cli_aggregates_the_simulated_humans_labels(tmp_path):
    rows = train(tmp_path / "run", "iterations=2", "dagger.episodes_per_iteration=2", "eval.episodes=1",
                 "eval.at_start=false", "task.max_episode_steps=25", "bc.updates_per_iteration=50",
                 "robot.options.control_hz=40.0", timeout=300)
    assert [r["step"] for r in rows] == [1, 2]
    for row in rows:
        for key in ("intervention/rate", "intervention/episode_rate", "intervention/takeovers_per_episode",
                    "rollout/success_rate", "eval/success_rate", "train/bc_loss", "dagger/dataset_rows"):
            assert key in row, key
        assert 0.0 <= row["intervention/rate"] <= 1.0
    # The dataset only grows, by the steps the human labelled (the initial demonstration's are in it first).
    assert rows[0]["dagger/dataset_rows"] >= rows[0]["dagger/added_rows"] > 0
    assert rows[1]["dagger/dataset_rows"] == rows[0]["dagger/dataset_rows"] + rows[1]["dagger/added_rows"]
    assert rows[1]["pipeline/version"] == 3  # the initial clone, then one version per iteration
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["dataset_rows"] == rows[1]["dagger/dataset_rows"]


@pytest.mark.slow
def test_hg_dagger_success_rises_and_interventions_fall(tmp_path):
    """The demo (infinirl/configs/hg_dagger_sawyer_reach.yaml): from a policy cloned on one
    demonstration, the simulated human's corrections teach it to reach: success rises, intervention
    rate falls."""
    rows = train(tmp_path / "demo", timeout=1200)
    evals = [r["eval/success_rate"] for r in rows if "eval/success_rate" in r]
    rates = [r["intervention/rate"] for r in rows if "intervention/rate" in r]
    assert max(evals[-3:]) >= evals[0] + 0.3
    assert sum(rates[-2:]) / 2 <= 0.5 * sum(rates[:2]) / 2


@pytest.mark.slow  # two runs of the command line
def test_hg_dagger_resumes_with_its_dataset(tmp_path):
    """Run again with more iterations: the learner (policy, optimiser, aggregate) comes back from the
    checkpoint, no demonstration is recorded again, and the dataset keeps growing from where it was."""
    small = ["dagger.episodes_per_iteration=1", "eval.episodes=1", "eval.at_start=false", "bc.updates_per_iteration=20",
             "task.max_episode_steps=20", "robot.options.control_hz=40.0"]
    first = train(tmp_path / "run", "iterations=1", *small, timeout=300)
    again = train(tmp_path / "run", "iterations=2", *small, timeout=300)
    assert [r["step"] for r in again] == [1, 2]
    assert again[1]["dagger/dataset_rows"] == first[0]["dagger/dataset_rows"] + again[1]["dagger/added_rows"]
    assert again[1]["pipeline/version"] == first[0]["pipeline/version"] + 1
