"""The one run loop every runner uses: resume, evaluate, step, log, checkpoint, finish.

A runner supplies its macro flow as a :class:`Flow` (what one iteration does, how it evaluates,
what its state is) and the loop does everything around it the same way for every runner::

    with RunLoop(cfg) as loop:              # driver-side checks: output folder, checkpoint, config
        ... start the cluster and the components ...
        return loop.run(flow)                # iterations, evaluations, checkpoints, summary

What the loop owns:

* **resume**: the newest checkpoint of ``output_dir`` (see :mod:`.checkpoints`) is checked before
  any worker starts: its files against their manifest, and the config it was written with against
  this one. A changed key that takes effect on resume (``RunConfig.resume_may_change``: length,
  cadences, loggers, placement, throughput settings) is applied and appended to
  ``config_history.jsonl``; any other change is refused, naming each key, because the restored
  state (optimizer, schedules, buffers) was built with the old value. The recorded config is read
  under the present key names (``RENAMED_KEYS``), and a key added since the checkpoint that holds
  its default counts as unchanged-in-effect (applied and recorded, shown as ``<absent> -> value``).
* **the iteration**: ``flow.step(i)``, a held-out evaluation every ``eval.every`` iterations and
  after the last (and at iteration 0 with ``eval.at_start``), metrics to every sink, a progress
  bar with the flow's fields and a line per evaluation, a checkpoint every ``save_every``
  iterations and at the end (``keep_checkpoints`` newest kept).
* **the end**: ``curves.png`` from the flow's panels, the flow's artifacts (an eval video, weight
  digests), and one JSON summary line: the headline metric before / after / best and the first
  evaluation that reached the target.
* **stopping early**: SIGINT (Ctrl-C) or SIGTERM (a scheduler's preemption) while iterations run
  asks the loop to stop after the current iteration: it writes a checkpoint there (unless one was
  just written), the curves and the summary (``stopped_at``), skips the flow's end artifacts and
  returns; ``infinirl train`` with the same config resumes from it. A second Ctrl-C interrupts at
  once.
* **starting over**: a run that starts at iteration 0 (``resume=false``, or no checkpoint yet) in a
  folder holding an earlier run's records moves them to ``earlier/<time>/`` first, so the old
  checkpoints are neither pruned among the new ones nor resumed later as this run's.
* **failure**: an output folder the run created and never logged to is removed again.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from infinirl.config import ConfigError, plain_default, to_plain, upgrade_renamed_keys
from infinirl.results import code_version, host_probe
from infinirl.runners.checkpoints import ABSENT, Checkpoints, config_changes
from infinirl.runners.curves import Panel, plot_panels
from infinirl.runners.metrics_log import METRICS_FILE, MetricsLogger, read_metrics
from infinirl.runners.run_config import RunConfig
from infinirl.runners.run_inputs import check_run_inputs, run_inputs
from infinirl.utils import (
    capture_rng_state,
    restore_rng_state,
    seed_everything,
    torch_save_atomic,
    write_json_atomic,
)

__all__ = ["Flow", "LoopSpec", "ProgressField", "RunLoop"]

DRIVER_RNG_FILE = "driver_rng.pt"
SUMMARY_FILE = "summary.json"
CONFIG_HISTORY_FILE = "config_history.jsonl"
EARLIER_RUNS_DIR = "earlier"
#: What a run writes into its output folder that a run starting over there would mix with its own.
EARLIER_RUN_RECORDS = ("checkpoints", METRICS_FILE, CONFIG_HISTORY_FILE, SUMMARY_FILE, "curves.png",
                       "config.json", "tensorboard", "wandb", "swanlab")


@dataclass(frozen=True, kw_only=True)
class ProgressField:
    label: str
    key: str
    format: str = ".2f"
    fallback: str | None = None
    """Shown when ``key`` has no value (e.g. the running return while no episode has ended yet)."""


@dataclass(frozen=True, kw_only=True)
class LoopSpec:
    """How the loop presents a flow."""

    name: str
    """Progress bar label."""
    title: str
    """Title of curves.png."""
    headline: str
    """The evaluation metric the summary reports (e.g. ``eval/success_rate``)."""
    target: float | None = None
    """The summary names the first evaluation whose headline metric reached this."""
    progress: tuple[ProgressField, ...] = ()
    panels: tuple[Panel, ...] = ()


class Flow(Protocol):
    """A runner's macro flow, as the loop drives it."""

    spec: LoopSpec

    def start(self, iteration: int) -> None:
        """Called once before the first iteration (0, or the resumed one): e.g. sync weights."""

    def step(self, iteration: int) -> dict:
        """One iteration (rollout, advantages, update, weight sync); returns its metrics."""

    def evaluate(self) -> dict:
        """Held-out evaluation of the current policy; ``eval/*`` metrics."""

    def save(self, folder: str) -> dict:
        """Write the components' state into ``folder``; return the driver's own state (JSON)."""

    def load(self, folder: str, state: dict) -> None:
        """Restore what :meth:`save` wrote."""

    def finish(self, output_dir: str) -> dict:
        """After the last iteration: artifacts (video) and digests for the summary."""


class RunLoop:
    def __init__(self, cfg: RunConfig, started: float | None = None, prepare: Callable[[], None] | None = None):
        self.cfg = cfg
        self.prepare = prepare
        """Makes what the run reads once the config is found resumable and before its inputs are
        recorded (the SFT runner generates its demonstrations): a first run records their digest,
        and a resumed one compares them with the checkpoint's."""
        self.started = started if started is not None else time.time()
        self.elapsed_before = 0.0
        self.checkpoints = Checkpoints(cfg.output_dir, keep=cfg.keep_checkpoints)
        self.logger: MetricsLogger | None = None
        self.resume_from: tuple[str, dict] | None = None
        self._history_record: dict | None = None
        self._created_output = False
        self.inputs: dict = {}
        """What the run reads besides its config (:mod:`.run_inputs`), recorded with each checkpoint."""

    # ------------------------------------------------------------------ before any worker starts
    def __enter__(self) -> RunLoop:
        self._created_output = not os.path.exists(self.cfg.output_dir)
        try:
            _check_writable(self.cfg.output_dir)
            self.resume_from = self._find_resume_point()
            if self.prepare is not None:
                self.prepare()
            self.inputs = run_inputs(self.cfg)
            if self.resume_from is None:
                self._set_earlier_run_aside()
            else:
                check_run_inputs(self.resume_from[1].get("inputs"), self.inputs, self.resume_from[0])
        except BaseException:
            self._remove_unused_output()
            raise
        seed_everything(self.cfg.seed)
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if error is not None and (self.logger is None or self.logger.rows_logged == 0):
            self._remove_unused_output()

    def _find_resume_point(self) -> tuple[str, dict] | None:
        found = self.checkpoints.latest() if self.cfg.resume else None
        if found is None:
            return None
        path, state = found
        iteration = _iteration_of(state)
        if self.cfg.iterations < iteration:
            raise ConfigError(f"iterations={self.cfg.iterations} is below the {iteration} iterations {path} has "
                              f"already run; set iterations >= {iteration} to resume it, or start over with "
                              "resume=false")
        recorded = state.get("config")
        if recorded is not None:
            self._check_config(path, recorded, iteration)
        metrics = os.path.join(self.cfg.output_dir, METRICS_FILE)
        if os.path.exists(metrics):
            # A damaged row is named now, before any worker starts; a last row cut off mid-write is
            # dropped (with a warning) when the logger reopens the file.
            read_metrics(metrics, warn=False)
        return found

    def _set_earlier_run_aside(self) -> None:
        """A run starting at iteration 0 in a folder holding an earlier run's records (``resume=false``,
        or a run that stopped before its first checkpoint) moves them to ``earlier/<time>/``: its
        checkpoints would otherwise be pruned with the new ones and resumed later as if they were
        this run's, and its metrics overwritten."""
        output = self.cfg.output_dir
        present = [name for name in EARLIER_RUN_RECORDS if os.path.lexists(os.path.join(output, name))]
        if not any(name in present for name in ("checkpoints", METRICS_FILE)):
            return
        stamp = time.strftime("%Y%m%dT%H%M%S")
        target = os.path.join(output, EARLIER_RUNS_DIR, stamp)
        suffix = 1
        while os.path.exists(target):
            suffix += 1
            target = os.path.join(output, EARLIER_RUNS_DIR, f"{stamp}-{suffix}")
        os.makedirs(target)
        for name in present:
            os.replace(os.path.join(output, name), os.path.join(target, name))
        print(f"starting over: the earlier run's records in {output} ({', '.join(present)}) moved to {target}",
              flush=True)

    def _check_config(self, path: str, recorded: dict, iteration: int) -> None:
        cls = type(self.cfg)
        # Recorded by an earlier version: its keys under their present names (RENAMED_KEYS), so a
        # rename alone is no change; a key added since (absent from the record) that holds its
        # default is what the checkpoint ran with, applied and recorded like a resumable change.
        recorded = upgrade_renamed_keys(cls, recorded, warn=False)
        changes = config_changes(recorded, to_plain(self.cfg))
        added = {k for k, (old, new) in changes.items() if old is ABSENT and new == plain_default(cls, k)}
        refused = {k: v for k, v in changes.items() if k not in added and not self.cfg.resume_may_change(k)}
        if refused:
            listed = "; ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in refused.items())
            hints = "".join(f" ({hint})" for hint in filter(None, map(self.cfg.resume_refusal_hint, refused)))
            raise ConfigError(f"resume: the config differs from the one {path} was written with ({listed}); the "
                              "checkpoint's state was built with the old values, so resuming would half-apply them"
                              f"{hints}. Restore those values to continue, or start over with resume=false (or a new "
                              "output_dir)")
        if changes:
            # Written once the run has resumed (``run``): a run that fails before that applied nothing.
            self._history_record = {"iteration": iteration, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                                    "changes": {k: {"old": old, "new": new} for k, (old, new) in changes.items()}}
            shown = ", ".join(f"{k} {old!r} -> {new!r}" for k, (old, new) in changes.items())
            print(f"resume: applying changed keys ({shown}); recorded in {CONFIG_HISTORY_FILE}", flush=True)

    def _record_config_changes(self) -> None:
        if self._history_record is None:
            return
        with open(os.path.join(self.cfg.output_dir, CONFIG_HISTORY_FILE), "a") as handle:
            handle.write(json.dumps(self._history_record, default=str) + "\n")
        self._history_record = None

    # ------------------------------------------------------------------ the loop
    def run(self, flow: Flow) -> dict:
        from tqdm import tqdm

        cfg, spec = self.cfg, flow.spec
        start = self._resume(flow)
        self.logger = MetricsLogger(cfg.output_dir, cfg.loggers, to_plain(cfg), start_step=start)
        flow.start(start)
        self._record_config_changes()
        latest_eval: dict = {}
        if start == 0 and cfg.eval.at_start:
            latest_eval = self._evaluate(flow, 0, None)
            self.logger.log({**latest_eval, "time/elapsed_s": self.elapsed()}, step=0)
        stopped_at = None
        with _StopRequests(spec.name) as stop, \
                tqdm(total=cfg.iterations, initial=start, desc=spec.name, unit="it", dynamic_ncols=True) as progress:
            for iteration in range(start, cfg.iterations):
                metrics = flow.step(iteration)
                done = iteration + 1
                if self._eval_due(done):
                    latest_eval = self._evaluate(flow, done, progress)
                    metrics.update(latest_eval)
                metrics["time/elapsed_s"] = self.elapsed()
                self.logger.log(metrics, step=done)
                progress.set_postfix_str(_postfix(spec.progress, {**latest_eval, **metrics}), refresh=False)
                progress.update()
                stopping = stop.requested is not None and done < cfg.iterations
                if (cfg.save_every and done % cfg.save_every == 0) or done == cfg.iterations or stopping:
                    path = self._save(flow, done)
                if stopping:
                    stopped_at = done
                    progress.write(f"{spec.name}: stopped by {stop.requested} after iteration {done}; checkpoint "
                                   f"{path}; run the same command again to resume")
                    break
        return self._finish(flow, stopped_at)

    def elapsed(self) -> float:
        """Wall time of the run so far, earlier runs of a resumed job included."""
        return self.elapsed_before + time.time() - self.started

    def _eval_due(self, done: int) -> bool:
        every = self.cfg.eval.every
        return (every and done % every == 0) or done == self.cfg.iterations

    def _evaluate(self, flow: Flow, iteration: int, progress) -> dict:
        if progress is not None:
            progress.set_description_str(f"{flow.spec.name} (evaluating)")
        start = time.perf_counter()
        result = dict(flow.evaluate())
        result.setdefault("time/eval_s", time.perf_counter() - start)
        shown = ", ".join(f"{k} {v:.4g}" for k, v in result.items()
                          if k.startswith("eval/") and isinstance(v, (int, float)))
        line = f"{flow.spec.name} iteration {iteration}: {shown}"
        if progress is not None:
            progress.set_description_str(flow.spec.name)
            progress.write(line)
        else:
            print(line, flush=True)
        return result

    # ------------------------------------------------------------------ checkpoints
    def _save(self, flow: Flow, iteration: int) -> str:
        tmp = self.checkpoints.begin(iteration)
        try:
            flow_state = flow.save(tmp)
            torch_save_atomic(capture_rng_state(), os.path.join(tmp, DRIVER_RNG_FILE))
            state = {"iteration": iteration, "elapsed_s": self.elapsed(), "config": to_plain(self.cfg),
                     "inputs": self.inputs, "flow": flow_state}
            return self.checkpoints.commit(tmp, iteration, state)
        except BaseException as exc:
            self.checkpoints.abandon(tmp)
            done = self.checkpoints.completed()
            kept = f"the previous checkpoint {done[-1][1]} is intact" if done else "no earlier checkpoint exists"
            exc.add_note(f"writing the checkpoint of iteration {iteration} failed; {kept}")
            raise

    def _resume(self, flow: Flow) -> int:
        if self.resume_from is None:
            return 0
        path, state = self.resume_from
        iteration = _iteration_of(state)
        flow.load(path, state.get("flow", state))
        rng = os.path.join(path, DRIVER_RNG_FILE)
        if os.path.exists(rng):
            import torch

            restore_rng_state(torch.load(rng, weights_only=False))
        elif "rng" in state:
            _restore_legacy_rng(state["rng"])
        self.elapsed_before = float(state.get("elapsed_s", 0.0))
        self.started = time.time()
        print(f"resumed from {path} at iteration {iteration}", flush=True)
        return iteration

    # ------------------------------------------------------------------ the end
    def _finish(self, flow: Flow, stopped_at: int | None = None) -> dict:
        cfg, spec = self.cfg, flow.spec
        artifacts = flow.finish(cfg.output_dir) if stopped_at is None else {}
        self.logger.close()
        rows = read_metrics(self.logger.path)
        curves = plot_panels(rows, spec.panels, os.path.join(cfg.output_dir, "curves.png"), spec.title)
        evals = [r for r in rows if _finite(r.get(spec.headline))]
        summary = {
            "iterations": cfg.iterations,
            **({} if stopped_at is None else {"stopped_at": stopped_at}),
            "elapsed_s": round(self.elapsed(), 1),
            "eval_metric": spec.headline,
            "eval_before": next((r[spec.headline] for r in evals if r["step"] == 0), None),
            "eval_after": evals[-1][spec.headline] if evals else None,
            "eval_best": max(r[spec.headline] for r in evals) if evals else None,
            "first_eval_at_target": _first_reaching(evals, spec.headline, spec.target),
            "curves": curves,
            "metrics": self.logger.path,
            **artifacts,
        }
        # For `infinirl record <output_dir>`: the result with what produced it, where, when it ended
        # and from which commit (none outside a git checkout).
        commit = code_version()
        write_json_atomic(os.path.join(cfg.output_dir, SUMMARY_FILE),
                          {**summary, "title": f"{spec.title} ({cfg.runner})", "command": _command_line(),
                           "host": host_probe(), "date": time.strftime("%Y-%m-%d"),
                           **({} if commit is None else {"commit": commit})})
        print(json.dumps(summary), flush=True)
        return summary

    def _remove_unused_output(self) -> None:
        if self._created_output and os.path.isdir(self.cfg.output_dir):
            shutil.rmtree(self.cfg.output_dir, ignore_errors=True)


class _StopRequests:
    """SIGINT and SIGTERM while iterations run: the first asks for a stop after the current
    iteration (``requested`` names the signal); a second SIGINT raises ``KeyboardInterrupt`` at
    once. Handlers can only be installed from the main thread; elsewhere nothing changes."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, name: str):
        self.name = name
        self.requested: str | None = None
        self._previous: dict = {}

    def __enter__(self) -> _StopRequests:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handle) for sig in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _handle(self, signum: int, frame) -> None:
        if self.requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name
        print(f"\n{self.name}: {self.requested} received; stopping after this iteration with a checkpoint "
              "(Ctrl-C again to interrupt at once)", file=sys.stderr, flush=True)


def _command_line() -> str:
    import shlex
    import sys

    argv = sys.argv or ["python"]
    program = os.path.basename(argv[0])
    return shlex.join(["infinirl" if program in ("infinirl", "cli.py") else program, *argv[1:]])


def _check_writable(output_dir: str) -> None:
    probe = os.path.join(output_dir, f".write-test-{os.getpid()}")
    try:
        os.makedirs(output_dir, exist_ok=True)
        with open(probe, "w"):
            pass
        os.remove(probe)
    except OSError as exc:
        raise ConfigError(f"output_dir={output_dir!r} cannot be written ({exc.strerror or exc}); "
                          "choose a folder you can write to") from None


def _iteration_of(state: dict) -> int:
    return int(state["iteration"] if "iteration" in state else state["step"])


def _restore_legacy_rng(state: dict) -> None:
    """The driver RNG as reasoning checkpoints stored it before the shared loop (JSON lists)."""
    import ast
    import random

    import numpy as np
    import torch

    random.setstate(ast.literal_eval(state["python"]))
    kind, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, np.array(keys, dtype=np.uint32), pos, has_gauss, gauss))
    torch.set_rng_state(torch.tensor(state["torch"], dtype=torch.uint8))


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def _postfix(fields: tuple[ProgressField, ...], metrics: dict) -> str:
    parts = []
    for field in fields:
        value = metrics.get(field.key)
        if not _finite(value) and field.fallback is not None:
            value = metrics.get(field.fallback)
        parts.append(f"{field.label}={format(value, field.format) if _finite(value) else '-'}")
    return ", ".join(parts)


def _first_reaching(evals: list[dict], key: str, target: float | None) -> dict | None:
    if target is None:
        return None
    for row in evals:
        if row[key] >= target:
            return {"iteration": row["step"], "env_steps": row.get("env/steps"), "elapsed_s": row.get("time/elapsed_s")}
    return None
