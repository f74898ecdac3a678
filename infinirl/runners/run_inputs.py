"""What a run reads besides its config that decides what it computes, recorded with each checkpoint
and compared on resume before any worker starts.

* **data files** the config names (``RunConfig.data_files``; the reasoning task's file, or a
  preset's files under ``$INFINIRL_DATA_DIR``), each with its size and sha256: a resumed data
  stream keeps only its position (epoch, offset) over the items, so other rows under the same
  count would be trained on silently, and another count would fail inside a worker;
* **what bfloat16 computes in on this host's CPU** (``engines/cpu_dtype``: ``INFINIRL_CPU_BF16``
  and the CPU's native bf16 support), when the config asks for bfloat16 anywhere and the run
  computes on the CPU (not recorded where the driver sees GPUs the cluster uses): on a CPU without
  native bf16 it becomes float32, so the same config can train at another precision on another
  host or with the variable changed.

A difference is a ConfigError naming the file (or the dtype keys) and the fix: a changed dtype is
refused like a changed key, since the restored state would continue at another precision.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

from infinirl.config import ConfigError, to_plain

__all__ = ["check_run_inputs", "file_digest", "run_inputs"]

_BF16 = ("bfloat16", "bf16")


def run_inputs(cfg) -> dict[str, Any]:
    """``{"data": {label: digest}, "bfloat16_on_cpu": {...}}`` of ``cfg`` on this host (each part
    only where it applies; a data file that does not exist is left to the runner's preflight)."""
    inputs: dict[str, Any] = {}
    data = {label: file_digest(path) for label, path in cfg.data_files().items() if Path(path).is_file()}
    if data:
        inputs["data"] = data
    keys = _bf16_keys(to_plain(cfg))
    if keys and not _on_gpus(cfg):
        from infinirl.engines.cpu_dtype import cpu_bf16_is_fast

        inputs["bfloat16_on_cpu"] = {"computes_in": "bfloat16" if cpu_bf16_is_fast() else "float32", "keys": keys}
    return inputs


def _on_gpus(cfg) -> bool:
    """Whether the run computes on GPUs, where bfloat16 is bfloat16 whatever the host's CPU: a GPU run
    moved to a host with another CPU is not refused for a precision its CPU never computed in."""
    import torch

    cluster = getattr(cfg, "cluster", None)
    return torch.cuda.is_available() and getattr(cluster, "num_gpus", None) != 0


def file_digest(path: str | os.PathLike) -> dict[str, Any]:
    """``{"path", "size", "sha256"}`` of a file (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return {"path": str(Path(path).resolve()), "size": os.path.getsize(path), "sha256": digest.hexdigest()}


def check_run_inputs(recorded: dict | None, current: dict, checkpoint: str) -> None:
    """ConfigError when ``current`` (this run's :func:`run_inputs`) differs from what ``checkpoint``
    recorded. Checkpoints written before inputs were recorded have none: nothing to compare."""
    if not recorded:
        return
    for label, was in (recorded.get("data") or {}).items():
        now = (current.get("data") or {}).get(label)
        if now is None or (now["size"], now["sha256"]) == (was["size"], was["sha256"]):
            continue  # a file gone or no longer named: the config check or the runner's preflight says so
        raise ConfigError(
            f"resume: {label} {now['path']} is not the file {checkpoint} trained on ({was['path']}: {was['size']} "
            f"bytes, sha256 {was['sha256'][:12]}; now {now['size']} bytes, sha256 {now['sha256'][:12]}); the "
            "restored data stream would go on over other problems; restore it (presets are read from "
            "$INFINIRL_DATA_DIR), or start over with resume=false (or a new output_dir)")
    was, now = recorded.get("bfloat16_on_cpu"), current.get("bfloat16_on_cpu")
    if was and now and was["computes_in"] != now["computes_in"]:
        fix = ("set INFINIRL_CPU_BF16=1 to keep bfloat16 on this CPU" if was["computes_in"] == "bfloat16" else
               "unset INFINIRL_CPU_BF16 and resume on a CPU without native bf16 (no AVX512-BF16/AMX), as it ran")
        raise ConfigError(
            f"resume: bfloat16 ({', '.join(now['keys'])}) computes in {now['computes_in']} on this host's CPU, in "
            f"{was['computes_in']} when {checkpoint} was written (INFINIRL_CPU_BF16 and the CPU's native bf16 decide "
            f"it), so the restored state would go on at another precision; {fix}, or start over with resume=false "
            "(or a new output_dir)")


def _bf16_keys(tree: Any, prefix: str = "") -> list[str]:
    """Dotted keys of a plain config whose name ends in ``dtype`` and whose value asks for bfloat16."""
    keys = []
    for key, value in (tree.items() if isinstance(tree, dict) else ()):
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            keys += _bf16_keys(value, path + ".")
        elif str(key).endswith("dtype") and isinstance(value, str) and value.lower() in _BF16:
            keys.append(path)
    return keys
