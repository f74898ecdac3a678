"""Per-rank crash logs: where a worker process's hard crash (segfault, abort) leaves its Python
stacks, so that the driver can quote the root cause of a rank that died.

One file per rank in ``CRASH_LOG_DIR`` on the rank's node, named by the group at launch
(``log_name``), so that the driver knows it even when the rank fails to start. Every process that
runs the rank (a restarted rank runs several, one after the other) appends a line
``# infinirl worker process <pid>`` and then its crash, if any: the driver quotes the section of
the process that died last (``last_process_crash``), reading the file on the rank's node
(``read_on_node``: by a Ray task there when that node is not the driver's).

Who removes them: the group, when it shuts down (or is garbage collected), removes the logs with
no crash in them; a log holding a crash is kept for the user. A driver killed outright removes
nothing, so the name also carries the launching process (host, pid, start time), and every launch
on that host removes the crash-free logs of launching processes that are gone
(``remove_orphaned``); logs of live launchers are never touched.
"""

from __future__ import annotations

import faulthandler
import os
import re
import socket
import tempfile
import uuid
from collections.abc import Iterable
from pathlib import Path

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from infinirl.runtime import processes
from infinirl.runtime.cancellation import cancel_quietly

__all__ = ["CRASH_LOG_DIR", "PROCESS_MARKER", "CrashLogUnreadable", "enable", "last_process_crash", "log_name",
           "read_on_node", "remove_if_no_crash", "remove_orphaned"]

CRASH_LOG_DIR = Path(tempfile.gettempdir()) / "infinirl-crash-logs"
PROCESS_MARKER = "# infinirl worker process "  # + pid: where each process's section of a crash log starts
_OWNER_TAG = ".launcher-"  # log_name: <component>-rank<r>-<id>.launcher-<host>-<pid>-<start>.log
# How long the driver waits for a task on another node to read a crash log there: a fresh worker
# process must start for it (a Cluster we start keeps no idle ones), seconds on a busy node.
READ_TIMEOUT_S = 30.0


class CrashLogUnreadable(Exception):
    """A rank's crash log is on another node and could not be read there; ``node_gone`` when that
    node has left the Ray cluster."""

    def __init__(self, message: str, node_gone: bool = False):
        super().__init__(message)
        self.node_gone = node_gone


def log_name(component: str, rank: int) -> str:
    """A fresh crash-log file name for one rank, tagged with the process launching it."""
    pid = os.getpid()
    owner = f"{_safe_host()}-{pid}-{processes.start_ticks(pid)}"
    return f"{component}-rank{rank}-{uuid.uuid4().hex[:12]}{_OWNER_TAG}{owner}.log"


def enable(component: str, rank: int, name: str) -> str:
    """In the rank's process: append this process's marker to its crash log and point
    ``faulthandler`` at it (hard crashes then write every thread's Python stack there)."""
    CRASH_LOG_DIR.mkdir(parents=True, exist_ok=True)
    path = CRASH_LOG_DIR / (name or f"{component}-rank{rank}-pid{os.getpid()}.log")
    handle = open(path, "a")  # kept open for the life of the process, as faulthandler needs
    handle.write(f"{PROCESS_MARKER}{os.getpid()}\n")
    handle.flush()
    faulthandler.enable(file=handle, all_threads=True)
    return str(path)


def last_process_crash(path: str | None, max_chars: int = 4000) -> tuple[int | None, str]:
    """(pid, crash text) of the last process that wrote to a rank's crash log: its section
    after its own marker line, empty if that process wrote no crash."""
    if not path:
        return None, ""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return None, ""
    _, marker, last = text.rpartition(PROCESS_MARKER)
    if not marker:
        return None, text.strip()[-max_chars:]
    pid_line, _, crash = last.partition("\n")
    return (int(pid_line) if pid_line.strip().isdigit() else None), crash.strip()[-max_chars:]


def read_on_node(log: str, node_id: str | None, timeout_s: float = READ_TIMEOUT_S) -> tuple[int | None, str]:
    """``last_process_crash`` of a rank's log, read on the rank's node: here when that is this
    process's node (or unknown), else by a task pinned to it. ``log`` is the path the rank
    reported, or the file name given at launch for one that died before it reported (resolved in
    ``CRASH_LOG_DIR`` on that node, whose temp dir can differ). Raises ``CrashLogUnreadable``
    when the node is gone or the task fails or takes over ``timeout_s``."""
    if not log:
        return None, ""
    if node_id is None or node_id == ray.get_runtime_context().get_node_id():
        return _last_process_crash_here(log)
    if not _node_alive(node_id):
        raise CrashLogUnreadable(f"node {node_id} has left the Ray cluster, and its crash log {log} with it",
                                 node_gone=True)
    task = ray.remote(num_cpus=0, max_retries=0)(_last_process_crash_here).options(
        scheduling_strategy=NodeAffinitySchedulingStrategy(node_id, soft=False))
    ref = task.remote(log)
    try:
        pid, crash = ray.get(ref, timeout=timeout_s)
        return pid, crash
    except ray.exceptions.GetTimeoutError:
        cancel_quietly(ref)
        raise CrashLogUnreadable(f"reading the crash log {log} on node {node_id} took over {timeout_s:g} s") from None
    except Exception as exc:
        gone = not _node_alive(node_id)
        why = "the node has left the Ray cluster" if gone else f"{type(exc).__name__}: {str(exc).strip()[:300]}"
        raise CrashLogUnreadable(f"the crash log {log} on node {node_id} could not be read ({why})",
                                 node_gone=gone) from None


def _last_process_crash_here(log: str) -> tuple[int | None, str]:
    return last_process_crash(log if os.path.isabs(log) else str(CRASH_LOG_DIR / log))


def _node_alive(node_id: str) -> bool:
    return any(node["NodeID"] == node_id and node["Alive"] for node in ray.nodes())


def remove_if_no_crash(paths: Iterable[str | None]) -> None:
    """Delete each crash log that holds nothing but its processes' marker lines (a rank on
    another node: not visible here, skipped)."""
    for path in paths:
        if not path:
            continue
        try:
            lines = Path(path).read_text(errors="replace").splitlines()
            if all(not line.strip() or line.startswith(PROCESS_MARKER) for line in lines):
                os.unlink(path)
        except OSError:
            pass


def remove_orphaned() -> list[str]:
    """Remove the crash-free logs whose launching process, on this host, is gone (e.g. a driver
    killed with SIGKILL: its groups never shut down). Returns the paths removed."""
    try:
        names = os.listdir(CRASH_LOG_DIR)
    except OSError:
        return []
    host = _safe_host()
    orphaned = []
    for name in names:
        owner = _owner(name)
        if owner is not None and owner[0] == host and not processes.alive(owner[1], owner[2]):
            orphaned.append(str(CRASH_LOG_DIR / name))
    remove_if_no_crash(orphaned)
    return [path for path in orphaned if not os.path.exists(path)]


def _owner(name: str) -> tuple[str, int, int] | None:
    """(host, pid, start ticks) of the process that launched the rank, from a ``log_name``."""
    _, tag, rest = name.rpartition(_OWNER_TAG)
    match = re.fullmatch(r"(.+)-(\d+)-(\d+)\.log", rest) if tag else None
    return (match[1], int(match[2]), int(match[3])) if match else None


def _safe_host() -> str:
    return re.sub(r"[^A-Za-z0-9.]", "_", socket.gethostname())
