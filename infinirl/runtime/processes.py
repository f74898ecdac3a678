"""Naming processes and telling whether one still runs.

- This process: the worker-host actor that runs in it, if any (a ``WorkerGroup`` rank's host
  registers itself when it starts; the driver and plain Ray tasks have none), and a label for
  error messages. ``p2p`` needs the host (only a host can serve pulls of its tensors);
  ``channel`` hands it to the channel, which watches it to learn when the process dies.
- Any process on this host: ``start_ticks(pid)`` and ``alive(pid, start)``; a pid together with
  its start time names one process, even after the pid is reused.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

__all__ = ["alive", "describe_self", "host_handle", "register_host", "start_ticks"]

_handle: Any = None
_label = ""


def register_host(handle: Any, label: str) -> None:
    """Called once by the worker host that runs in this process (``label``: e.g. ``actor[rank 1]``)."""
    global _handle, _label
    _handle, _label = handle, label


def host_handle() -> Any:
    """This process's worker-host actor handle, or None outside a worker rank."""
    return _handle


def describe_self() -> str:
    """This process for an error message: ``actor[rank 1] (pid 123 on host h)`` or ``pid 123 on host h``."""
    where = f"pid {os.getpid()} on host {socket.gethostname()}"
    return f"{_label} ({where})" if _label else where


def start_ticks(pid: int) -> int:
    """When process ``pid`` started, in clock ticks since boot (Linux ``/proc``): 0 where that is
    unknown, -1 for a process that has exited (gone, or a zombie)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return -1
    except OSError:
        return 0
    fields = stat.rpartition(")")[2].split()  # the command name in parentheses may hold spaces
    if fields and fields[0] in ("Z", "X"):
        return -1
    return int(fields[19]) if len(fields) > 19 else 0


def alive(pid: int, start: int = 0) -> bool:
    """Whether the process ``pid`` that started at ``start`` (``start_ticks``; 0: any) still runs."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's process: it exists
    now = start_ticks(pid)
    return now != -1 and (start == 0 or now in (0, start))
