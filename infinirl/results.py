"""Measured results into ``docs/results.md``, written by the tools that measure them.

Every run writes ``summary.json`` (its final JSON line plus the command that started it and a
probe of the host); every benchmark ends with a JSON line with ``ratios`` and takes
``--record docs/results.md``. This module turns either into a results entry (what, command, host,
date, result) and appends it to the results file, so numbers are never copied by hand::

    infinirl record runs/ppo_metaworld_reach            # a run's summary
    python benchmarks/embodied_pipeline.py --record docs/results.md
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path
from typing import Any

__all__ = ["RECORDED_SECTION", "append_entry", "format_entry", "host_probe", "record_run"]

RECORDED_SECTION = "## Recorded by the tools"


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


def format_entry(*, title: str, command: str, result: dict, host: dict, date: str | None = None) -> str:
    """A results entry in the file's format: title, what, command, host, date, the result as JSON."""
    date = date or time.strftime("%Y-%m-%d")
    gpus = ", ".join(host.get("gpus") or []) or "no GPU"
    host_line = (f"{host.get('cpu', 'unknown CPU')}, {host.get('vcpus', '?')} vCPUs, "
                 f"{host.get('memory_gib', '?')} GiB, {gpus}; torch {host.get('torch', '?')}")
    shown = {k: v for k, v in result.items() if k not in ("command", "host")}
    return (f"### {title}\n\n"
            f"Command: `{command}`.\n"
            f"Host: {host_line}. Date: {date}.\n\n"
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
    entry = format_entry(title=title or result.get("title") or source.name, command=result.get("command", "?"),
                         result=result, host=result.get("host") or host_probe())
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
