"""Files and folders that appear whole or not at all.

Every file a run writes for later (checkpoints, replay buffers, configs, traces, videos) goes to a
temporary name in the same folder and is renamed into place: a rename within one filesystem is
atomic, so a reader (or a resumed run after a crash, a full disk or ``kill -9``) sees the old
file or the complete new one, never a torn one. The temporary file is removed on any error. The
file gets the permissions a plain ``open`` would give it (``0o666`` less the umask), not the
owner-only ones of a temporary file, so a checkpoint is as readable as any other output.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_open", "atomic_path", "fsync_directory", "fsync_tree", "new_file_mode", "replace_directory",
           "torch_save_atomic", "write_json_atomic", "write_text_atomic"]

_umask_lock = threading.Lock()


def new_file_mode() -> int:
    """The mode ``open(path, "w")`` gives a new file: ``0o666`` less the process's umask."""
    try:  # Linux reports the umask without changing it
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except OSError:
        pass
    with _umask_lock:  # elsewhere: read it by setting it (and put it back at once)
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


def fsync_directory(path: str | os.PathLike) -> None:
    """Make a created/renamed entry of ``path`` durable (the rename itself is in the directory)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _temporary_beside(path: str, suffix: str, permissions: int | None = None) -> tuple[int, str]:
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{os.path.basename(path)}.", suffix=suffix)
    os.fchmod(fd, new_file_mode() if permissions is None else permissions)  # mkstemp makes it 0o600
    return fd, tmp


@contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb", suffix: str = ".tmp",
                durable: bool = False, permissions: int | None = None) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing; on a clean exit it replaces ``path``.

    ``suffix`` ends the temporary name (writers that pick a format by extension need it, e.g.
    ``".tmp.mp4"``). ``durable``: ``fsync`` the data before the rename and the folder after it, so
    the new file survives a power loss too (replay buffers, whose contents cannot be recomputed).
    ``permissions``: the new file's mode bits, set before any byte is written (e.g. ``0o600`` for a
    private key; default: what a plain ``open`` gives)."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open writes whole files: mode must be 'w' or 'wb', got {mode!r}")
    path = os.fspath(path)
    fd, tmp = _temporary_beside(path, suffix, permissions)
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
            handle.flush()
            if durable:
                os.fsync(handle.fileno())
        os.replace(tmp, path)
        if durable:  # the rename lives in the folder: without this a power loss may undo it
            fsync_directory(os.path.dirname(os.path.abspath(path)))
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[str]:
    """A temporary file name beside ``path`` for writers that open files themselves (e.g. a video
    encoder picking its format by extension); on a clean exit the file replaces ``path``."""
    path = os.fspath(path)
    fd, tmp = _temporary_beside(path, suffix)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    with atomic_open(path, "w") as handle:
        handle.write(text)


def write_json_atomic(path: str | os.PathLike, data: Any) -> None:
    """``data`` as indented JSON (values JSON cannot hold are written as their ``str``)."""
    with atomic_open(path, "w") as handle:
        json.dump(data, handle, indent=2, default=str)
        handle.write("\n")


def torch_save_atomic(obj: Any, path: str | os.PathLike, durable: bool = False) -> None:
    import torch

    with atomic_open(path, "wb", durable=durable) as handle:
        torch.save(obj, handle)


def fsync_tree(path: str | os.PathLike) -> None:
    """``fsync`` every file and folder under ``path`` (folders after their contents, ``path``
    last), so what a rename then publishes is on the disk, not only in the page cache."""
    for directory, _, files in os.walk(path, topdown=False):
        for name in files:
            fd = os.open(os.path.join(directory, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_directory(directory)


def replace_directory(new: str | os.PathLike, target: str | os.PathLike, durable: bool = False) -> None:
    """Move folder ``new`` to ``target``, replacing an existing ``target``.

    Two renames cannot be one atomic step: the old ``target`` is kept as ``<target>.old`` until the
    new one is in place, so at every moment one complete folder exists under one of the names.
    ``durable``: every file and folder of ``new`` is fsynced before the rename and the parent
    folder after it, before the old one is deleted: after a power loss the folder holds its
    bytes (a rename is ordered before the data it names by nothing else), or the old one is there."""
    new, target = Path(new), Path(target)
    old = target.with_name(target.name + ".old")
    if durable:
        fsync_tree(new)
    if target.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(target, old)
    os.replace(new, target)
    if durable:
        fsync_directory(target.parent)
    shutil.rmtree(old, ignore_errors=True)
