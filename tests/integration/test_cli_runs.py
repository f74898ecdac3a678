"""The command line as a user runs it: its own process, its own Ray."""

import pytest


@pytest.mark.slow  # default-tier budget; run with pytest -m slow
def test_runtime_demo_cli_trains_end_to_end(tmp_path):
    """`infinirl train runtime_demo` as a user runs it (own process, own Ray): the loss falls, trace is written."""
    import json
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "infinirl.cli", "train", "runtime_demo", "iterations=8", f"output_dir={tmp_path}",
         "cluster.log_to_driver=false"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 8
    assert rows[-1]["rollout/policy_loss"] < 0.5 * rows[0]["rollout/policy_loss"]
    assert max(r["rollout/max_staleness"] for r in rows) <= 1
    trace = json.loads((tmp_path / "trace.json").read_text())
    assert {e["name"] for e in trace["traceEvents"] if e["ph"] == "X"} >= {"produce", "train"}

