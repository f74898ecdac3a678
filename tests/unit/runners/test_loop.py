"""The shared run loop, driven by a toy flow (no Ray): cadences, checkpoints, exact resume, config
changes on resume, a full disk mid-checkpoint, and output folders of failed runs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pytest

from infinirl.config import ConfigError, bounded, to_dataclass
from infinirl.results import code_version
from infinirl.runners.curves import Panel
from infinirl.runners.loop import LoopSpec, ProgressField, RunLoop
from infinirl.runners.run_config import RunConfig


@dataclass(kw_only=True)
class ToyConfig(RunConfig):
    RUNNER: ClassVar[str] = "toy"
    DEFAULT_PLACEMENT: ClassVar[dict[str, str]] = {"learner": "0"}
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = ("batch",)

    output_dir: str = "runs/toy"
    lr: float = bounded(0.1, gt=0)
    batch: int = bounded(8, ge=1)
    loggers: list[str] = field(default_factory=list)


class ToyFlow:
    """SGD on a noisy linear target; its state is the weights and its own generator."""

    def __init__(self, cfg: ToyConfig, fail_at: int | None = None):
        self.cfg, self.fail_at = cfg, fail_at
        self.w = np.zeros(3)
        self.rng = np.random.default_rng(cfg.seed)
        self.spec = LoopSpec(name="toy", title="toy", headline="eval/score", target=0.9,
                             progress=(ProgressField(label="loss", key="train/loss"),),
                             panels=(Panel(title="loss", y=("train/loss",)),))
        self.started_at = None

    def start(self, iteration: int) -> None:
        self.started_at = iteration

    def step(self, iteration: int) -> dict:
        if iteration == self.fail_at:
            raise RuntimeError("the step failed")
        x = self.rng.normal(size=(self.cfg.batch, 3))
        y = x @ np.array([1.0, -2.0, 0.5]) + 0.01 * self.rng.normal(size=self.cfg.batch)
        error = x @ self.w - y
        self.w -= self.cfg.lr * x.T @ error / self.cfg.batch
        return {"train/loss": float(np.mean(error**2))}

    def evaluate(self) -> dict:
        return {"eval/score": float(1.0 / (1.0 + np.sum((self.w - np.array([1.0, -2.0, 0.5])) ** 2)))}

    def save(self, folder: str) -> dict:
        np.save(os.path.join(folder, "w.npy"), self.w)
        return {"rng": self.rng.bit_generator.state}

    def load(self, folder: str, state: dict) -> None:
        self.w = np.load(os.path.join(folder, "w.npy"))
        self.rng.bit_generator.state = state["rng"]

    def finish(self, output_dir: str) -> dict:
        return {"weights": self.w.tolist()}


def toy(tmp_path, **raw) -> ToyConfig:
    return to_dataclass(ToyConfig, {"output_dir": str(tmp_path / "run"), **raw})


def run(cfg: ToyConfig, **flow_options) -> dict:
    with RunLoop(cfg) as loop:
        return loop.run(ToyFlow(cfg, **flow_options))


def rows_of(cfg: ToyConfig) -> list[dict]:
    return [json.loads(line) for line in open(os.path.join(cfg.output_dir, "metrics.jsonl"))]


def test_cadences_checkpoints_and_summary(tmp_path, capsys):
    cfg = toy(tmp_path, iterations=6, save_every=2, keep_checkpoints=2, **{"eval": {"every": 3}})
    summary = run(cfg)
    rows = rows_of(cfg)
    assert [r["step"] for r in rows] == [0, 1, 2, 3, 4, 5, 6]
    assert [r["step"] for r in rows if "eval/score" in r] == [0, 3, 6]
    assert sorted(os.listdir(os.path.join(cfg.output_dir, "checkpoints"))) == ["iter_000004", "iter_000006"]
    assert summary["eval_metric"] == "eval/score" and summary["iterations"] == 6
    assert summary["eval_before"] == rows[0]["eval/score"] and summary["eval_after"] == rows[-1]["eval/score"]
    assert summary["eval_best"] == max(r["eval/score"] for r in rows if "eval/score" in r)
    assert summary["weights"] and os.path.exists(summary["curves"])
    out = capsys.readouterr().out
    assert "toy iteration 3: eval/score" in out  # each evaluation leaves a line in the log
    assert json.loads(out.strip().splitlines()[-1]) == summary
    # summary.json adds what `infinirl record` needs: the command, host, end date and commit
    written = json.load(open(os.path.join(cfg.output_dir, "summary.json")))
    assert written["date"] == time.strftime("%Y-%m-%d") and written.get("commit") == code_version()


def test_no_initial_evaluation_means_no_before_value(tmp_path):
    summary = run(toy(tmp_path, iterations=2, **{"eval": {"every": 1, "at_start": False}}))
    assert summary["eval_before"] is None and summary["eval_after"] is not None


def test_resume_continues_exactly(tmp_path):
    straight = run(toy(tmp_path / "a", iterations=6, save_every=3))
    run(toy(tmp_path / "b", iterations=3, save_every=3))
    resumed = run(toy(tmp_path / "b", iterations=6, save_every=3))
    assert resumed["weights"] == straight["weights"]
    a, b = rows_of(toy(tmp_path / "a")), rows_of(toy(tmp_path / "b"))
    assert [r["train/loss"] for r in a[1:]] == [r["train/loss"] for r in b[1:]]
    # iterations 3 -> 6 is a change that takes effect: applied and recorded, and config.json tells the truth
    history = [json.loads(line) for line in open(tmp_path / "b" / "run" / "config_history.jsonl")]
    assert history[-1]["iteration"] == 3 and history[-1]["changes"] == {"iterations": {"old": 3, "new": 6}}
    assert json.load(open(tmp_path / "b" / "run" / "config.json"))["iterations"] == 6


class SignalledFlow(ToyFlow):
    """Sends its own process ``signals`` (one each) during the step of iteration ``at``."""

    def __init__(self, cfg, at: int, signals: tuple[int, ...]):
        super().__init__(cfg)
        self.at, self.signals = at, signals

    def step(self, iteration: int) -> dict:
        for sig in self.signals if iteration == self.at else ():
            os.kill(os.getpid(), sig)
        return super().step(iteration)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_the_run_after_its_iteration_with_a_checkpoint_and_resume_is_exact(tmp_path, sig):
    straight = run(toy(tmp_path / "a", iterations=6, save_every=5))
    before = signal.getsignal(sig)
    cfg = toy(tmp_path / "b", iterations=6, save_every=5)
    with RunLoop(cfg) as loop:
        stopped = loop.run(SignalledFlow(cfg, at=2, signals=(sig,)))
    assert signal.getsignal(sig) is before  # the loop's handler is gone again
    assert stopped["stopped_at"] == 3 and "weights" not in stopped  # no end artifacts for a stopped run
    assert sorted(os.listdir(os.path.join(cfg.output_dir, "checkpoints"))) == ["iter_000003"]
    assert [r["step"] for r in rows_of(cfg)] == [0, 1, 2, 3]
    resumed = run(cfg)
    assert "stopped_at" not in resumed and resumed["weights"] == straight["weights"]
    assert [r["train/loss"] for r in rows_of(cfg)[1:]] == [r["train/loss"] for r in rows_of(toy(tmp_path / "a"))[1:]]


def test_a_second_ctrl_c_interrupts_at_once(tmp_path):
    cfg = toy(tmp_path, iterations=6)
    before = signal.getsignal(signal.SIGINT)  # Python's default, or SIG_IGN in a job started in the background
    with pytest.raises(KeyboardInterrupt), RunLoop(cfg) as loop:
        loop.run(SignalledFlow(cfg, at=1, signals=(signal.SIGINT, signal.SIGINT)))
    assert signal.getsignal(signal.SIGINT) is before  # the loop's handler is gone again
    assert not os.path.exists(os.path.join(cfg.output_dir, "checkpoints")) or \
        not os.listdir(os.path.join(cfg.output_dir, "checkpoints"))


def test_a_changed_key_the_checkpoint_cannot_honour_is_refused_before_anything_runs(tmp_path):
    run(toy(tmp_path, iterations=2))
    with pytest.raises(ConfigError, match=r"resume: the config differs from the one .*iter_000002 was written with "
                                          r"\(lr: 0.1 -> 0.5\).*start over with resume=false"):
        run(toy(tmp_path, iterations=4, lr=0.5))
    config = json.load(open(tmp_path / "run" / "config.json"))
    assert config["lr"] == 0.1  # never claims what did not happen
    run(toy(tmp_path, iterations=4, batch=16))  # a throughput key this runner declares safe: applied
    run(toy(tmp_path, iterations=4, lr=0.5, resume=False))  # starting over is always possible


def test_resume_after_a_crash_mid_log_keeps_each_step_once(tmp_path, capsys):
    """Killed while writing step 5's row, after its checkpoint at 3: resuming drops the cut-off row
    and the rows and TensorBoard steps past the checkpoint, so every step is there once."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = toy(tmp_path, iterations=6, save_every=3, loggers=["tensorboard"], **{"eval": {"every": 0}})
    with pytest.raises(RuntimeError, match="the step failed"):
        run(cfg, fail_at=4)
    with open(os.path.join(cfg.output_dir, "metrics.jsonl"), "a") as handle:
        handle.write('{"step": 5, "train/lo')
    run(cfg)
    assert "line 6 was cut off mid-write" in capsys.readouterr().err
    assert [r["step"] for r in rows_of(cfg)] == [0, 1, 2, 3, 4, 5, 6]
    events = EventAccumulator(os.path.join(cfg.output_dir, "tensorboard"))
    events.Reload()
    assert [e.step for e in events.Scalars("train/loss")] == [1, 2, 3, 4, 5, 6]


def test_a_damaged_metrics_row_is_refused_before_anything_runs(tmp_path):
    cfg = toy(tmp_path, iterations=4, save_every=2)
    run(toy(tmp_path, iterations=2))
    path = os.path.join(cfg.output_dir, "metrics.jsonl")
    lines = open(path).read().splitlines(keepends=True)
    with open(path, "w") as handle:
        handle.write(lines[0] + "{garbage\n" + "".join(lines[1:]))
    with pytest.raises(ConfigError, match=r"metrics.jsonl line 2 is not a JSON row"):
        with RunLoop(cfg):
            raise AssertionError("workers would start here")


def test_a_failed_run_removes_the_output_folder_it_created_but_keeps_one_with_results(tmp_path):
    cfg = toy(tmp_path, iterations=3, **{"eval": {"at_start": False}})
    with pytest.raises(RuntimeError, match="the step failed"):
        run(cfg, fail_at=0)
    assert not os.path.exists(cfg.output_dir)
    with pytest.raises(RuntimeError, match="the step failed"):
        run(cfg, fail_at=2)
    assert [r["step"] for r in rows_of(cfg)] == [1, 2]  # what was logged stays for the post-mortem


def test_an_unwritable_output_folder_is_a_config_error(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match=r"output_dir=.*file/run' cannot be written"):
        run(toy(tmp_path / "file", iterations=1))


def test_a_full_disk_while_checkpointing_keeps_the_previous_checkpoint(tmp_path):
    """A real write error from the kernel (RLIMIT_FSIZE: EFBIG, as a full disk gives ENOSPC) in the
    second checkpoint: the run stops, names the checkpoint that survives, and that one resumes."""
    script = textwrap.dedent(f"""
        import os, resource, signal, sys
        import numpy as np
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_loop import ToyFlow, toy, RunLoop
        from pathlib import Path

        class BigFlow(ToyFlow):
            def save(self, folder):
                state = super().save(folder)
                np.save(os.path.join(folder, "big.npy"), np.zeros(1_000_000 * int(self.w[0] != 0 and self.grow)))
                return state

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing us
        resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, 1_000_000))
        cfg = toy(Path({str(tmp_path)!r}), iterations=4, save_every=2)
        with RunLoop(cfg) as loop:
            flow = BigFlow(cfg)
            flow.grow = False
            original_step = flow.step
            def step(iteration):
                flow.grow = iteration >= 2
                return original_step(iteration)
            flow.step = step
            loop.run(flow)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert proc.returncode != 0
    assert "OSError" in proc.stderr, proc.stderr[-2000:]  # the short write the file-size limit caused
    assert "writing the checkpoint of iteration 4 failed; the previous checkpoint iter_000002 is intact" in proc.stderr
    checkpoints = tmp_path / "run" / "checkpoints"
    assert sorted(os.listdir(checkpoints)) == ["iter_000002"]  # no half-written folder left
    summary = run(toy(tmp_path, iterations=4, save_every=2))  # and it resumes
    assert summary["iterations"] == 4


def test_starting_over_moves_the_earlier_runs_records_aside(tmp_path, capsys):
    """resume=false in a folder with an earlier run's checkpoints: pruning must not delete the new
    run's checkpoints in favour of the old ones, nor a later resume pick the old run up."""
    earlier = run(toy(tmp_path, iterations=4, save_every=2))
    cfg = toy(tmp_path, iterations=2, save_every=2, keep_checkpoints=1, resume=False)
    run(cfg)
    assert "starting over: the earlier run's records" in capsys.readouterr().out
    assert os.listdir(os.path.join(cfg.output_dir, "checkpoints")) == ["iter_000002"]
    [stamp] = os.listdir(os.path.join(cfg.output_dir, "earlier"))
    kept = os.path.join(cfg.output_dir, "earlier", stamp)
    assert sorted(os.listdir(os.path.join(kept, "checkpoints"))) == ["iter_000002", "iter_000004"]
    assert json.load(open(os.path.join(kept, "summary.json")))["weights"] == earlier["weights"]
    assert [r["step"] for r in rows_of(cfg)] == [0, 1, 2]
    resumed = run(toy(tmp_path, iterations=4, save_every=2))  # resumes the new run, not the earlier one
    assert "resumed from" in capsys.readouterr().out and resumed["weights"] == earlier["weights"]
    assert [r["step"] for r in rows_of(cfg)] == [0, 1, 2, 3, 4]


def test_a_length_below_what_the_checkpoint_ran_is_refused(tmp_path):
    run(toy(tmp_path, iterations=4, save_every=4))
    with pytest.raises(ConfigError, match=r"iterations=2 is below the 4 iterations .*iter_000004 has already run; "
                                          r"set iterations >= 4 to resume it, or start over with resume=false"):
        run(toy(tmp_path, iterations=2))


class FailsToStart(ToyFlow):
    def start(self, iteration: int) -> None:
        raise RuntimeError("the cluster did not start")


def test_a_config_change_is_recorded_only_once_the_run_resumed(tmp_path):
    run(toy(tmp_path, iterations=2))
    cfg = toy(tmp_path, iterations=4, batch=16)
    with pytest.raises(RuntimeError, match="did not start"), RunLoop(cfg) as loop:
        loop.run(FailsToStart(cfg))
    history = os.path.join(cfg.output_dir, "config_history.jsonl")
    assert not os.path.exists(history)  # nothing was applied
    run(cfg)
    assert [json.loads(line)["changes"] for line in open(history)] == [
        {"batch": {"old": 8, "new": 16}, "iterations": {"old": 2, "new": 4}}]


def test_an_embodied_run_annealing_over_its_length_cannot_be_lengthened_on_resume(tmp_path):
    from infinirl.config import to_plain
    from infinirl.runners.embodied_config import EmbodiedConfig

    def embodied(**raw) -> EmbodiedConfig:
        return to_dataclass(EmbodiedConfig, {"env": {"name": "metaworld:reach-v3", "num_envs": 4}, "rollout_steps": 8,
                                             "output_dir": str(tmp_path / "run"), **raw})

    recorded = to_plain(embodied(iterations=2))
    with pytest.raises(ConfigError, match=r"\(iterations: 2 -> 4\).*half-apply them \(the learning rate decays to 0 "
                                          r"over iterations .*start it with actor.anneal_iterations"):
        RunLoop(embodied(iterations=4))._check_config("ckpt", recorded, 2)
    RunLoop(embodied(iterations=4, actor={"anneal_lr": False}))._check_config(
        "ckpt", to_plain(embodied(iterations=2, actor={"anneal_lr": False})), 2)
    RunLoop(embodied(iterations=4, actor={"anneal_iterations": 8}))._check_config(
        "ckpt", to_plain(embodied(iterations=2, actor={"anneal_iterations": 8})), 2)


def _edit_recorded_config(output_dir: str, edit) -> None:
    """Rewrite the config the newest checkpoint recorded (and its manifest), as an older version of
    the code would have written it."""
    from infinirl.runners.checkpoints import MANIFEST_FILE, STATE_FILE, Checkpoints, _manifest

    path, state = Checkpoints(output_dir).latest()
    edit(state["config"])
    with open(os.path.join(path, STATE_FILE), "w") as handle:
        json.dump(state, handle)
    with open(os.path.join(path, MANIFEST_FILE), "w") as handle:
        json.dump(_manifest(path), handle)


@dataclass(kw_only=True)
class RenamedToyConfig(ToyConfig):
    RENAMED_KEYS: ClassVar[dict[str, str]] = {"rate": "lr"}


def test_a_checkpoint_recorded_under_a_renamed_key_resumes(tmp_path, capsys):
    cfg = to_dataclass(RenamedToyConfig, {"output_dir": str(tmp_path / "run"), "iterations": 2, "lr": 0.05})
    run(cfg)
    _edit_recorded_config(cfg.output_dir, lambda recorded: recorded.update(rate=recorded.pop("lr")))
    run(to_dataclass(RenamedToyConfig, {"output_dir": str(tmp_path / "run"), "iterations": 4, "lr": 0.05}))
    history = [json.loads(line)["changes"] for line in open(tmp_path / "run" / "config_history.jsonl")]
    assert history == [{"iterations": {"old": 2, "new": 4}}]
    assert "'rate' is now 'lr'" not in capsys.readouterr().err  # a record is upgraded silently: nobody can rename it
    _edit_recorded_config(cfg.output_dir, lambda recorded: recorded.update(rate=recorded.pop("lr")))
    with pytest.raises(ConfigError, match=r"\(lr: 0.05 -> 0.1\)"):  # the upgraded value is still compared
        run(to_dataclass(RenamedToyConfig, {"output_dir": str(tmp_path / "run"), "iterations": 6}))


def test_a_key_added_since_the_checkpoint_resumes_at_its_default_and_is_recorded(tmp_path):
    run(toy(tmp_path, iterations=2))
    _edit_recorded_config(str(tmp_path / "run"), lambda recorded: recorded.pop("lr"))  # written before `lr` existed
    run(toy(tmp_path, iterations=3))
    history = [json.loads(line)["changes"] for line in open(tmp_path / "run" / "config_history.jsonl")]
    assert history == [{"iterations": {"old": 2, "new": 3}, "lr": {"old": "<absent>", "new": 0.1}}]
    _edit_recorded_config(str(tmp_path / "run"), lambda recorded: recorded.pop("lr"))
    with pytest.raises(ConfigError, match=r"\(lr: <absent> -> 0.2\); the checkpoint's state was built"):
        run(toy(tmp_path, iterations=4, lr=0.2))  # not the default: the checkpoint did not run with it


def test_a_reasoning_checkpoint_written_before_is_cap_was_renamed_resumes(tmp_path):
    """algorithm.objective.tis_cap is now is_cap (ReasoningConfig.RENAMED_KEYS): a checkpoint that
    recorded the old name holds the same setting, not a change of two keys."""
    from infinirl.config import to_plain
    from infinirl.runners.reasoning_config import ReasoningConfig

    cfg = to_dataclass(ReasoningConfig, {"output_dir": str(tmp_path / "run"),
                                         "algorithm": {"objective": {"is_cap": 2.0}}})
    recorded = to_plain(cfg)
    objective = recorded["algorithm"]["objective"]
    objective["tis_cap"] = objective.pop("is_cap")
    loop = RunLoop(cfg)
    loop._check_config("ckpt", recorded, 2)
    assert loop._history_record is None  # nothing changed
    objective["tis_cap"] = 3.0
    with pytest.raises(ConfigError, match=r"algorithm.objective.is_cap: 3.0 -> 2.0"):
        loop._check_config("ckpt", recorded, 2)
