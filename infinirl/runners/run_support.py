"""What every runner's driver does the same way: when the run started, starting its components
together, and checkpoint folders that appear whole or not at all.

Kept out of the runners so that the reasoning, embodied and SAC macro flows read as their
algorithm and nothing else, and so a fix here (say, to the checkpoint commit) reaches all of them.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from concurrent.futures import ThreadPoolExecutor

__all__ = ["CheckpointFolders", "launch_all", "run_start_time"]

_RUNS_IN_PROCESS = [0]
_STATE_FILE = "runner_state.json"


def run_start_time() -> float:
    """Wall-clock origin of ``time/elapsed_s``: the process start for the first run in a process
    (so interpreter and import start-up count, as a user timing the command sees them), the call
    for later ones (tests run several runs in one process)."""
    _RUNS_IN_PROCESS[0] += 1
    if _RUNS_IN_PROCESS[0] == 1:
        try:
            import psutil

            return psutil.Process().create_time()
        except Exception:
            pass
    return time.time()


def launch_all(plan, launches: dict):
    """Start every component at once (their start-up, mostly imports, overlaps).

    ``launches``: component name -> (Worker class, constructor args) or (Worker class, constructor
    args, environment variables of its processes from their start). If any component fails to
    start, the ones that did are shut down and the first error is raised (its root cause, not a
    secondary "actor died" from a sibling)."""
    from infinirl.runtime import WorkerGroup

    with ThreadPoolExecutor(len(launches)) as pool:
        futures = {name: pool.submit(WorkerGroup.launch, cls, name, placement=plan.ranks(name), args=args,
                                     env_vars=env_vars[0] if env_vars else None)
                   for name, (cls, args, *env_vars) in launches.items()}
        groups, error = {}, None
        for name, future in futures.items():
            try:
                groups[name] = future.result()
            except BaseException as exc:  # keep the first error, stop what did start
                error = error or exc
    if error is not None:
        for group in groups.values():
            group.shutdown()
        raise error
    return groups


class CheckpointFolders:
    """``<output_dir>/checkpoints/<prefix>NNNNNN/``, each built under ``.tmp`` and renamed into
    place, with the driver's own state in ``runner_state.json``: a crash at any point leaves the
    previous checkpoint usable, and a half-written folder is never mistaken for one."""

    def __init__(self, output_dir: str, prefix: str):
        self.root = os.path.join(output_dir, "checkpoints")
        self.prefix = prefix

    def begin(self, index: int) -> str:
        """An empty temporary folder for checkpoint ``index``; components write into it."""
        tmp = self._final(index) + ".tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        os.makedirs(tmp)
        return tmp

    def commit(self, tmp: str, index: int, state: dict) -> str:
        """Write the driver's ``state`` and rename the folder into place; the final path."""
        with open(os.path.join(tmp, _STATE_FILE), "w") as handle:
            json.dump(state, handle)
        final = self._final(index)
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
        return final

    def completed(self) -> list[str]:
        """Names of the committed checkpoints, oldest first."""
        if not os.path.isdir(self.root):
            return []
        return sorted(d for d in os.listdir(self.root) if d.startswith(self.prefix) and not d.endswith(".tmp"))

    def latest(self) -> tuple[str, dict] | None:
        """(path, driver state) of the newest committed checkpoint, or None."""
        done = self.completed()
        if not done:
            return None
        path = os.path.join(self.root, done[-1])
        with open(os.path.join(path, _STATE_FILE)) as handle:
            return path, json.load(handle)

    def prune(self, keep: int) -> None:
        """Delete all but the newest ``keep`` checkpoints."""
        for old in self.completed()[:-keep]:
            shutil.rmtree(os.path.join(self.root, old), ignore_errors=True)

    def _final(self, index: int) -> str:
        return os.path.join(self.root, f"{self.prefix}{index:06d}")
