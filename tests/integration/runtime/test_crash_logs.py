"""Crash logs left by a launcher that is gone (a driver killed outright) are removed; no others.
A rank on another node is reported with the crash log of that node."""

import json
import os
import secrets
import subprocess
import sys

import pytest

from infinirl.runtime import crash_logs, processes

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def _name_from_a_process_that_exits() -> str:
    code = "from infinirl.runtime import crash_logs; print(crash_logs.log_name('actor', 0))"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (REPO, os.environ.get("PYTHONPATH")) if p)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    return out.stdout.strip()


def test_remove_orphaned_removes_only_crash_free_logs_of_gone_launchers(tmp_path, monkeypatch):
    monkeypatch.setattr(crash_logs, "CRASH_LOG_DIR", tmp_path)
    marker = f"{crash_logs.PROCESS_MARKER}12345\n"
    gone = _name_from_a_process_that_exits()
    gone_with_crash = _name_from_a_process_that_exits()
    mine = crash_logs.log_name("actor", 1)
    host = mine.rpartition(".launcher-")[2].rsplit("-", 2)[0]
    start = processes.start_ticks(os.getpid())
    reused_pid = mine.replace(f"-{os.getpid()}-{start}.log", f"-{os.getpid()}-{start - 1}.log")  # an older process
    other_host = gone.replace(f".launcher-{host}-", ".launcher-elsewhere-")
    untagged = "actor-rank0-pid999999.log"
    for name in (gone, gone_with_crash, mine, reused_pid, other_host, untagged):
        (tmp_path / name).write_text(marker)
    (tmp_path / gone_with_crash).write_text(marker + "Fatal Python error: Segmentation fault\n")

    removed = crash_logs.remove_orphaned()

    assert sorted(removed) == sorted(str(tmp_path / n) for n in (gone, reused_pid))
    assert sorted(os.listdir(tmp_path)) == sorted([gone_with_crash, mine, other_host, untagged])


def test_process_identity_tells_a_reused_pid_apart():
    me = os.getpid()
    started = processes.start_ticks(me)
    assert processes.alive(me, started) and processes.alive(me)
    assert not processes.alive(me, started + 1)  # another process that had this pid before
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                              text=True, check=True)
    assert not processes.alive(int(finished.stdout))


@pytest.mark.slow  # starts two Ray nodes; run with pytest -m slow tests/integration
def test_a_rank_on_another_node_is_reported_with_that_nodes_crash_log():
    """The second node's crash-log folder is its own (see the scenario): read on the driver's disk,
    the log is not there, and the rank would be reported as an opaque death."""
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32),
           "PYTHONPATH": os.pathsep.join(p for p in (REPO, os.environ.get("PYTHONPATH")) if p)}
    env.pop("RAY_ADDRESS", None)
    scenario = os.path.join(REPO, "tests", "integration", "runtime", "scenarios", "remote_crash_log.py")
    proc = subprocess.run([sys.executable, scenario], capture_output=True, text=True, timeout=540, cwd=REPO, env=env)
    assert proc.returncode == 0, proc.stderr[-4000:]
    out = json.loads([ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1].removeprefix("RESULT "))
    if "skip" in out:
        pytest.skip(out["skip"])
    assert out["rank_node"] != out["driver_node"] and not out["log_on_driver_disk"]
    crashed = out["crashed"]
    assert "sim[rank 0].segfault() died (process exited)" in crashed, crashed
    assert "Segmentation fault" in crashed and "in segfault" in crashed, crashed
    gone = out["node_gone"]
    assert "lost[rank 0].sleep() died (its node left the Ray cluster)" in gone, gone
    assert out["node_gone_s"] < 60
