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



PENDULUM = ["env.name=gym:Pendulum-v1", "env.num_envs=2", "rollout_steps=16", "save_every=0", "algorithm.epochs=1",
            "algorithm.mini_batches=2", "eval.every=0", "eval.episodes=2", "eval.num_envs=1", "eval.video_episodes=0",
            "eval.env_kwargs={}", "loggers=[]", "cluster.log_to_driver=false"]


def start_until(command: list[str], metrics, rows: int):
    """``command`` in a session of its own (a terminal's process group), once ``metrics`` has ``rows`` lines."""
    import subprocess
    import time

    proc = subprocess.Popen(command, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    deadline = time.monotonic() + 240
    while not (metrics.exists() and len(metrics.read_text().splitlines()) >= rows) and proc.poll() is None:
        assert time.monotonic() < deadline, f"the run logged no iteration {rows} in 240 s"
        time.sleep(0.1)
    return proc


@pytest.mark.slow  # default-suite budget: two whole CLI runs in subprocesses
def test_ctrl_c_or_sigterm_stops_after_the_iteration_with_a_checkpoint_and_the_run_resumes(tmp_path):
    """Ctrl-C reaches the driver and the Ray processes it started (the terminal's process group);
    a scheduler's SIGTERM reaches the driver: both end the run after the current iteration, with a
    checkpoint there, exit 0, and the same command resumes from it. Here Ctrl-C stops the first
    run, the same command resumes it, and SIGTERM stops that one."""
    import json
    import os
    import signal
    import sys

    pytest.importorskip("gymnasium")
    command = [sys.executable, "-m", "infinirl.cli", "train", "ppo_metaworld_reach", *PENDULUM,
               f"output_dir={tmp_path}", "iterations=400"]
    metrics, checkpoints = tmp_path / "metrics.jsonl", tmp_path / "checkpoints"
    stops = []
    for signal_name, whom in (("SIGINT", "group"), ("SIGTERM", "driver")):
        resumed_from = stops[-1] if stops else None
        proc = start_until(command, metrics, (resumed_from or 1) + 1)
        if whom == "group":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=180)
        assert proc.returncode == 0, err[-3000:]
        stopped = json.loads((tmp_path / "summary.json").read_text())["stopped_at"]
        assert (resumed_from or 1) + 1 <= stopped < 400
        assert f"stopped by {signal_name} after iteration {stopped}" in out + err
        if resumed_from:
            assert f"resumed from {checkpoints / f'iter_{resumed_from:06d}'} at iteration {resumed_from}" in out
        stops.append(stopped)
        assert sorted(os.listdir(checkpoints)) == [f"iter_{s:06d}" for s in stops]
        assert [json.loads(line)["step"] for line in metrics.read_text().splitlines()] == list(range(1, stopped + 1))
