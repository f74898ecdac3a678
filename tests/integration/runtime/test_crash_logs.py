"""Crash logs left by a launcher that is gone (a driver killed outright) are removed; no others."""

import os
import subprocess
import sys

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
