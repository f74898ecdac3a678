"""Checkpoint folders of a run: ``<output_dir>/checkpoints/iter_NNNNNN/``, whole or absent.

A checkpoint is built in ``iter_NNNNNN.tmp`` (components write their state into it), then the
driver writes its own state (``runner_state.json``: iteration, clock, the config the run had, the
flow's counters) and a ``manifest.json`` listing every file with its size, and renames the folder
into place. A crash, ``kill -9`` or a full disk at any point leaves the previous checkpoint usable,
a half-written folder is never mistaken for one, and a file truncated afterwards is named on
resume instead of failing deep inside a worker. Every file and folder of the new checkpoint is
fsynced before its rename and the checkpoints folder after it, and only then are older
checkpoints pruned, so a power loss leaves the new checkpoint whole or the previous one.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from typing import Any

from infinirl.config import ConfigError
from infinirl.utils import replace_directory, write_json_atomic

__all__ = ["ABSENT", "Checkpoints", "config_changes", "verify_checkpoint"]

STATE_FILE = "runner_state.json"
MANIFEST_FILE = "manifest.json"
PREFIX = "iter_"
# Reasoning runs wrote step_NNNNNN before the runners shared one loop; they still resume.
LEGACY_PREFIXES = ("step_",)
_NAME = re.compile(r"^(iter_|step_)(\d+)$")


class Checkpoints:
    def __init__(self, output_dir: str, keep: int = 0):
        self.root = os.path.join(output_dir, "checkpoints")
        self.keep = keep

    def begin(self, index: int) -> str:
        """An empty temporary folder for checkpoint ``index``; components write into it."""
        tmp = self.path_of(index) + ".tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        os.makedirs(tmp)
        return tmp

    def commit(self, tmp: str, index: int, state: dict) -> str:
        """Write the driver's ``state`` and the manifest, rename the folder into place, prune; the final path."""
        write_json_atomic(os.path.join(tmp, STATE_FILE), state)
        write_json_atomic(os.path.join(tmp, MANIFEST_FILE), _manifest(tmp))
        final = self.path_of(index)
        # Durable before the older checkpoints are pruned: without the fsyncs a power loss could
        # leave the new folder renamed into place with empty files and the older ones deleted.
        # A same-numbered folder is kept aside until the new one is in place.
        replace_directory(tmp, final, durable=True)
        if self.keep:
            self.prune(self.keep)
        return final

    def abandon(self, tmp: str) -> None:
        shutil.rmtree(tmp, ignore_errors=True)

    def completed(self) -> list[tuple[int, str]]:
        """``(index, folder name)`` of the committed checkpoints, oldest first."""
        if not os.path.isdir(self.root):
            return []
        found = []
        for name in os.listdir(self.root):
            match = _NAME.match(name)
            if match and os.path.isdir(os.path.join(self.root, name)):
                found.append((int(match.group(2)), name))
        return sorted(found)

    def latest(self) -> tuple[str, dict] | None:
        """``(path, driver state)`` of the newest checkpoint, checked against its manifest; None if there is none."""
        done = self.completed()
        if not done:
            return None
        path = os.path.join(self.root, done[-1][1])
        return path, verify_checkpoint(path)

    def prune(self, keep: int) -> None:
        """Delete all but the newest ``keep`` checkpoints."""
        for _, name in self.completed()[:-keep]:
            shutil.rmtree(os.path.join(self.root, name), ignore_errors=True)

    def path_of(self, index: int) -> str:
        return os.path.join(self.root, f"{PREFIX}{index:06d}")


def _manifest(folder: str) -> dict[str, int]:
    sizes = {}
    for directory, _, files in os.walk(folder):
        for name in files:
            path = os.path.join(directory, name)
            sizes[os.path.relpath(path, folder)] = os.path.getsize(path)
    sizes.pop(MANIFEST_FILE, None)
    return dict(sorted(sizes.items()))


def verify_checkpoint(folder: str, fix: str | None = None) -> dict:
    """The driver state of the committed checkpoint ``folder``, after its files are checked against
    its manifest. A missing, unreadable, truncated or altered file is a ConfigError naming it and
    ``fix`` (default: how to resume without this checkpoint), so resume and ``infinirl eval`` refuse
    the same damage before any worker reads it."""
    state = _read_state(folder, fix)
    _verify_manifest(folder, fix)
    return state


def _unusable(folder: str, file: str, why: str, fix: str | None = None) -> ConfigError:
    fix = fix or f"start over with resume=false, or delete {folder} to resume from the checkpoint before it"
    return ConfigError(f"checkpoint file {file} {why}; {fix}")


def _read_state(folder: str, fix: str | None = None) -> dict:
    path = os.path.join(folder, STATE_FILE)
    try:
        with open(path) as handle:
            state = json.load(handle)
    except FileNotFoundError:
        raise _unusable(folder, path, "is missing", fix) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _unusable(folder, path, f"is not valid JSON ({exc})", fix) from None
    if not isinstance(state, dict):
        raise _unusable(folder, path, "does not hold a mapping", fix)
    return state


def _verify_manifest(folder: str, fix: str | None = None) -> None:
    path = os.path.join(folder, MANIFEST_FILE)
    if not os.path.exists(path):  # written by a version without manifests: nothing to compare
        return
    try:
        with open(path) as handle:
            expected = json.load(handle)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _unusable(folder, path, f"is not valid JSON ({exc})", fix) from None
    if not isinstance(expected, dict):
        raise _unusable(folder, path, "does not hold a mapping", fix)
    for relative, size in expected.items():
        file = os.path.join(folder, relative)
        if not os.path.isfile(file):
            raise _unusable(folder, file, "is missing", fix)
        actual = os.path.getsize(file)
        if actual != size:
            raise _unusable(folder, file, f"is truncated or altered ({actual} bytes, written with {size})", fix)


def config_changes(old: dict, new: dict, prefix: str = "") -> dict[str, tuple[Any, Any]]:
    """Every dotted key whose value differs between two plain config trees: ``key -> (old, new)``;
    a key one tree lacks has :data:`ABSENT` there (shown as ``<absent>``, not as a null value)."""
    changes: dict[str, tuple[Any, Any]] = {}
    for key in sorted(set(old) | set(new), key=str):
        path = f"{prefix}{key}"
        a, b = old.get(key, ABSENT), new.get(key, ABSENT)
        if isinstance(a, dict) and isinstance(b, dict):
            changes.update(config_changes(a, b, path + "."))
        elif a != b:
            changes[path] = (a, b)
    return changes


class _Absent:
    """A key one of two compared configs lacks (a key added or removed since the checkpoint)."""

    def __repr__(self) -> str:
        return "<absent>"

    __str__ = __repr__  # config_history.jsonl writes it with str


ABSENT = _Absent()
