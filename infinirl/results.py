"""Measured results into ``docs/results.md``, written by the tools that measure them.

Every run writes ``summary.json`` (its final JSON line plus the command that started it, a probe of
the host, the date it ended and the commit of the code, see ``code_version``); every benchmark ends
with a JSON line with ``ratios`` and takes ``--record docs/results.md``. This module turns either
into a results entry (what, command, host, date, commit, result) and appends it to the results
file, so numbers are never copied by hand. A run stopped before its last iteration (``stopped_at``
in its summary) is recorded marked as stopped, in its title and in a line of its own::

    infinirl record runs/ppo_metaworld_reach            # a run's summary
    python benchmarks/embodied_pipeline.py --record docs/results.md
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

__all__ = ["RECORDED_SECTION", "append_entry", "code_version", "format_entry", "host_probe", "record_run"]

RECORDED_SECTION = "## Recorded by the tools"

# The checkout this package runs from, when it runs from one (not from an installed wheel).
_CHECKOUT = Path(__file__).resolve().parent.parent


def code_version(checkout: str | os.PathLike = _CHECKOUT) -> str | None:
    """The commit of the code that ran: ``git rev-parse --short HEAD`` of ``checkout``, with
    ``-dirty`` when a tracked file differs from that commit (untracked files, such as run folders,
    do not count). None when ``checkout`` is not the top of a git work tree (an installed package:
    a repository that merely encloses site-packages is not the code's) or git is missing, so an
    entry then names no commit rather than a wrong one."""
    checkout = Path(checkout).resolve()

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(checkout), *args], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != checkout:
        return None
    commit = git("rev-parse", "--short", "HEAD")
    if not commit:
        return None  # a repository with no commit yet
    changes = git("status", "--porcelain", "--untracked-files=no")
    return f"{commit}-dirty" if changes else commit


def host_probe() -> dict[str, Any]:
    """What the machine is: CPU model and count, memory, accelerators, library versions."""
    probe: dict[str, Any] = {"cpu": _cpu_model(), "vcpus": len(os.sched_getaffinity(0)),
                             "memory_gib": _memory_gib(), "python": platform.python_version()}
    try:
        import torch

        probe["torch"] = torch.__version__
        probe["gpus"] = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
    except ImportError:
        probe["gpus"] = []
    return probe


def format_entry(*, title: str, command: str, result: dict, host: dict, date: str | None = None,
                 commit: str | None = None) -> str:
    """A results entry in the file's format: title, command, host, date, commit (omitted when
    None: not a git checkout), the result as JSON. A result with ``stopped_at`` (a run stopped by a
    signal before its last iteration) is marked as such in the title and in a line of its own."""
    date = date or time.strftime("%Y-%m-%d")
    gpus = ", ".join(host.get("gpus") or []) or "no GPU"
    host_line = (f"{host.get('cpu', 'unknown CPU')}, {host.get('vcpus', '?')} vCPUs, "
                 f"{host.get('memory_gib', '?')} GiB, {gpus}; torch {host.get('torch', '?')}")
    commit_part = f" Commit: `{commit}`." if commit else ""
    stopped = ""
    if result.get("stopped_at") is not None:
        of = f" of {result['iterations']}" if result.get("iterations") is not None else ""
        title = f"{title} (stopped at iteration {result['stopped_at']}{of})"
        stopped = (f"Stopped: a signal ended the run after iteration {result['stopped_at']}{of}, so this is not the "
                   "full run (no end artifacts).\n")
    shown = {k: v for k, v in result.items() if k not in ("command", "host", "date", "commit")}
    return (f"### {title}\n\n"
            f"Command: `{command}`.\n"
            f"Host: {host_line}. Date: {date}.{commit_part}\n"
            f"{stopped}\n"
            f"```json\n{json.dumps(shown, indent=1, sort_keys=True, default=str)}\n```\n")


def append_entry(path: str | os.PathLike, entry: str) -> None:
    """Append ``entry`` under the results file's section of tool-written entries (created if absent)."""
    from infinirl.utils import write_text_atomic

    path = Path(path)
    text = path.read_text() if path.exists() else "# Measured results\n"
    if RECORDED_SECTION not in text:
        text = text.rstrip("\n") + f"\n\n{RECORDED_SECTION}\n\nEntries appended by `infinirl record` and the " \
                                   "benchmarks' `--record`, newest last.\n"
    write_text_atomic(path, text.rstrip("\n") + "\n\n" + entry)


def record_run(source: str | os.PathLike, to: str | os.PathLike, title: str | None = None) -> str:
    """Append the entry of a run folder's ``summary.json`` (or of a JSON file) to ``to``; the entry."""
    source = Path(source)
    file = source / "summary.json" if source.is_dir() else source
    if not file.is_file():
        raise FileNotFoundError(f"{file} does not exist: a run writes summary.json when it finishes; pass a finished "
                                "run's output_dir or a benchmark's JSON line saved to a file")
    result = _read_result(file)
    # The date the run ended, not today's: a summary written before runs recorded it dates from its
    # file, written as the run ended. Its commit is not guessed: today's checkout may be another.
    date = result.get("date") or time.strftime("%Y-%m-%d", time.localtime(file.stat().st_mtime))
    entry = format_entry(title=title or result.get("title") or source.name, command=result.get("command", "?"),
                         result=result, host=result.get("host") or host_probe(), date=date,
                         commit=result.get("commit"))
    append_entry(to, entry)
    return entry


def _read_result(file: Path) -> dict:
    """The JSON object in ``file``: the whole file (a summary.json), or else its last line, so a
    benchmark's saved stdout works too (benchmarks print their result as the last line)."""
    text = file.read_text(errors="replace")
    lines = [line for line in text.splitlines() if line.strip()]
    for candidate in (text, lines[-1] if lines else ""):
        try:
            result = json.loads(candidate)
            break
        except json.JSONDecodeError:
            continue
    else:
        raise ValueError(f"{file} holds no JSON result: it must hold a run's summary.json object, or a benchmark's "
                         "saved output whose last line is the JSON it prints; pass such a file")
    if not isinstance(result, dict):
        raise ValueError(f"{file} holds a JSON {type(result).__name__}, not the result object a run's summary.json "
                         "or a benchmark's last line holds; pass that file instead")
    return result


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> float | None:
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        return None
    return round(pages * size / 2**30, 1)
