"""scripts/compare_runs.py: several runs' metrics in one figure, a line per run, and its one-line
refusals (a run without metrics, a malformed LABEL=RUN_DIR, metrics no run logged)."""

import json
import os
import sys

import pytest

SCRIPTS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "scripts")
sys.path.insert(0, SCRIPTS)

from compare_runs import labelled_rows, main  # noqa: E402


def write_run(path, successes):
    path.mkdir()
    with open(path / "metrics.jsonl", "w") as f:
        for step, success in successes.items():
            f.write(json.dumps({"step": step, "eval/success_rate": success, "rollout/success_rate": 0.5}) + "\n")
    return str(path)


def test_each_runs_metrics_become_a_line_of_its_own_with_the_start_point_first():
    runs = {"a": [{"step": 20, "x": 0.6, "y": 1.0}, {"time": 3.0}], "b": [{"step": 20, "x": 0.7}]}
    assert labelled_rows(runs, ["x", "y"], start=0.5) == [
        {"step": 0, "x|a": 0.5}, {"step": 20, "x|a": 0.6, "y|a": 1.0},
        {"step": 0, "x|b": 0.5}, {"step": 20, "x|b": 0.7}]
    assert labelled_rows(runs, ["y"], start=None) == [{"step": 20, "y|a": 1.0}, {"step": 20}]


def test_it_draws_the_runs_into_one_png(tmp_path):
    seed0 = write_run(tmp_path / "s0", {20: 0.6, 40: 0.7})
    seed1 = write_run(tmp_path / "s1", {20: 0.5, 40: 0.8})
    out = tmp_path / "compare.png"
    main([f"seed 0={seed0}", f"seed 1={seed1}", "--panel", "eval/success_rate:held-out success",
          "--panel", "rollout/success_rate", "--start", "0.51", "--target", "0.76", "--out", str(out)])
    with open(out, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, message", [
    (["nolabel", "--panel", "x"], "is not LABEL=RUN_DIR"),
    (["a={missing}", "--panel", "x"], "metrics.jsonl not found"),
    (["a={run}", "--panel", "never/logged"], "none of the runs logged ['never/logged']"),
    (["a={run}", "--panel", "eval/success_rate", "--panel", "typo"], "none of the runs logged ['typo']"),
])
def test_what_it_cannot_draw_is_refused_in_one_line(tmp_path, capsys, args, message):
    run = write_run(tmp_path / "run", {20: 0.6})
    args = [a.format(run=run, missing=tmp_path / "missing") for a in args]
    with pytest.raises(SystemExit) as exit_:
        main([*args, "--out", str(tmp_path / "out.png")])
    assert message in str(exit_.value) and "\n" not in str(exit_.value)
