"""What a run reads besides its config that decides what it computes, recorded with each checkpoint
and compared on resume before any worker starts.

* **data files and folders** the config names (``RunConfig.data_files``: the reasoning task's
  file, or a preset's files under ``$INFINIRL_DATA_DIR``; a cloning dataset, a checkpoint folder
  a run starts from), a file with its size and sha256, a folder with its total size and a tree
  digest (each file's relative path, size and sha256; temporary files of an unfinished write left
  out): a resumed data stream keeps only its position (epoch, offset) over the items, so other rows
  under the same count would be trained on silently, and another count would fail inside a worker;
  a resumed model built from other statistics or weights would go on from another start;
* **what bfloat16 computes in on this host's CPU** (``engines/cpu_dtype``: ``INFINIRL_CPU_BF16``
  and the CPU's native bf16 support), when the config asks for bfloat16 anywhere and the run
  computes on the CPU (not recorded where the driver sees GPUs the cluster uses): on a CPU without
  native bf16 it becomes float32, so the same config can train at another precision on another
  host or with the variable changed.

A difference is a ConfigError naming the key, the file or folder (or the dtype keys) and the fix:
a changed dtype is refused like a changed key, since the restored state would continue at another
precision. ``infinirl eval run_dir=...`` compares a run's task file with what its checkpoint
recorded in the same way (:func:`data_differences`).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

from infinirl.config import ConfigError, to_plain

__all__ = ["check_run_inputs", "data_differences", "data_digests", "describe_difference", "file_digest",
           "path_digest", "run_inputs", "tree_digest"]

_BF16 = ("bfloat16", "bf16")


def run_inputs(cfg) -> dict[str, Any]:
    """``{"data": {label: digest}, "bfloat16_on_cpu": {...}}`` of ``cfg`` on this host (each part
    only where it applies; a data path that does not exist is left to the runner's preflight)."""
    inputs: dict[str, Any] = {}
    data = data_digests(cfg.data_files())
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


def data_digests(paths: dict[str, str]) -> dict[str, dict[str, Any]]:
    """``label -> digest`` of each path that exists (:func:`path_digest`)."""
    return {label: path_digest(path) for label, path in paths.items() if Path(path).exists()}


def path_digest(path: str | os.PathLike) -> dict[str, Any]:
    """:func:`tree_digest` of a folder, :func:`file_digest` of a file."""
    return tree_digest(path) if Path(path).is_dir() else file_digest(path)


def file_digest(path: str | os.PathLike) -> dict[str, Any]:
    """``{"path", "size", "sha256"}`` of a file (read in 1 MiB blocks)."""
    return {"path": str(Path(path).resolve()), "size": os.path.getsize(path), "sha256": _sha256(path)}


# sha256 of files already read by this process, by what identifies their contents (device, inode,
# size, modification and change times): a run records its inputs at the start and with every
# checkpoint, and a multi-GB checkpoint folder would otherwise be read again each time. Any write
# to a file moves its change time, which no user call can set back.
_SHA256_SEEN: dict[tuple, str] = {}


def _sha256(path: str | os.PathLike) -> str:
    info = os.stat(path)
    key = (info.st_dev, info.st_ino, info.st_size, info.st_mtime_ns, info.st_ctime_ns)
    if key not in _SHA256_SEEN:
        _SHA256_SEEN[key] = _read_sha256(path)
    return _SHA256_SEEN[key]


def _read_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _temporary(name: str) -> bool:
    """A write in progress or abandoned beside its target (``utils.atomic``'s ``.<name>.XXXX.tmp``
    files, the ``.<name>.tmp-XXXX`` folders of the dataset writer and ``save_vla``): not content."""
    return name.startswith(".") and ".tmp" in name


def tree_digest(path: str | os.PathLike) -> dict[str, Any]:
    """``{"path", "size", "sha256", "files"}`` of a folder: ``sha256`` over every file's relative
    path, size and sha256 in path order (so a renamed, added or removed file changes it as a changed
    byte does), ``size`` their total; temporary files (:func:`_temporary`) are left out."""
    root = Path(path)
    entries = []
    for folder, folders, files in os.walk(root):
        folders[:] = sorted(name for name in folders if not _temporary(name))
        for name in files:
            if not _temporary(name):
                file = Path(folder) / name
                entries.append((file.relative_to(root).as_posix(), os.path.getsize(file), _sha256(file)))
    digest = hashlib.sha256()
    for relative, size, sha in sorted(entries):
        digest.update(f"{relative}\0{size}\0{sha}\n".encode())
    return {"path": str(root.resolve()), "size": sum(size for _, size, _ in entries), "sha256": digest.hexdigest(),
            "files": len(entries)}


def data_differences(recorded: dict | None, current: dict) -> list[tuple[str, dict, dict]]:
    """``(label, recorded digest, current digest)`` of each data path whose contents differ; a path
    gone or no longer named is left out (the config check or the runner's preflight says so)."""
    changed = []
    for label, was in (recorded or {}).items():
        now = (current or {}).get(label)
        if now is not None and (now["size"], now["sha256"]) != (was["size"], was["sha256"]):
            changed.append((label, was, now))
    return changed


def describe_difference(label: str, was: dict, now: dict, written: str) -> str:
    """``<label> <path> is not the file <written> (...)``: one line naming both contents."""
    kind = "folder" if "files" in now else "file"
    return (f"{label} {now['path']} is not the {kind} {written} ({was['path']}: {was['size']} bytes, sha256 "
            f"{was['sha256'][:12]}; now {now['size']} bytes, sha256 {now['sha256'][:12]})")


def check_run_inputs(recorded: dict | None, current: dict, checkpoint: str) -> None:
    """ConfigError when ``current`` (this run's :func:`run_inputs`) differs from what ``checkpoint``
    recorded. Checkpoints written before inputs were recorded have none: nothing to compare."""
    if not recorded:
        return
    for label, was, now in data_differences(recorded.get("data"), current.get("data")):
        raise ConfigError(
            f"resume: {describe_difference(label, was, now, checkpoint + ' trained on')}; the restored state would go "
            "on over other data; restore it, or start over with resume=false (or a new output_dir)")
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
