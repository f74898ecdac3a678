"""Metrics sinks write what was logged: JSONL, TensorBoard, W&B (offline) and SwanLab (local).

Each test logs a few steps through `MetricsLogger`, closes it, and reads the values back from the
files the sink wrote (W&B and SwanLab both keep a LevelDB-log file of protobuf records), so a sink
that silently drops or mangles metrics fails here, not in a user's dashboard.
"""

import glob
import importlib.util
import json
import re
import struct
import time
import zlib

import numpy as np
import pytest
import torch

from infinirl.runners.metrics_log import CONFIG_FILE, MetricsLogger, read_metrics

STEPS = {1: {"train/loss": 1.5, "eval/greedy_accuracy": 0.25},
         2: {"train/loss": np.float32(0.75), "eval/greedy_accuracy": 0.5},
         3: {"train/loss": torch.tensor(0.375), "eval/greedy_accuracy": 1, "note": "not a number"}}
EXPECTED = {step: {k: float(v) for k, v in row.items() if k != "note"} for step, row in STEPS.items()}
CONFIG = {"lr": 1e-3, "model": {"path": "tiny"}}


def log_steps(output_dir, loggers):
    logger = MetricsLogger(str(output_dir), loggers, CONFIG)
    for step, metrics in STEPS.items():
        logger.log(metrics, step=step)
    logger.close()
    logger.close()  # idempotent
    return logger


def leveldb_log_records(path, block=32 * 1024, header=7):
    """Records of a LevelDB-log file (the format of ``.wandb`` and ``.swanlab`` run files)."""
    data = open(path, "rb").read()
    pos, out, pending = header, [], b""
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # the block's tail is padding
            pos += block - pos % block
            continue
        crc, length, kind = struct.unpack("<IHB", data[pos : pos + 7])
        if length == 0 and kind == 0:
            pos += block - pos % block
            continue
        if pos + 7 + length > len(data):  # still being written
            break
        chunk = data[pos + 7 : pos + 7 + length]
        assert zlib.crc32(chunk, zlib.crc32(bytes([kind]))) & 0xFFFFFFFF == crc, "corrupt record"
        pos += 7 + length
        pending += chunk
        if kind in (1, 4):  # FULL or LAST
            out.append(pending)
            pending = b""
    return out


def wait_for_records(path, record_cls, last, timeout_s=60.0):
    """Parsed records once the run's ``last`` record is on disk: W&B's service process may still be
    writing its transaction log when ``finish()`` returns."""
    deadline = time.monotonic() + timeout_s
    while True:
        records = []
        for raw in leveldb_log_records(path):
            records.append(record_cls())
            records[-1].ParseFromString(raw)
        if any(r.WhichOneof("record_type") == last for r in records) or time.monotonic() > deadline:
            return records
        time.sleep(0.2)


def test_jsonl_and_config_are_written(tmp_path):
    log_steps(tmp_path, [])
    rows = read_metrics(str(tmp_path / "metrics.jsonl"))
    assert {r["step"]: {k: v for k, v in r.items() if k != "step"} for r in rows} == EXPECTED
    assert json.loads((tmp_path / CONFIG_FILE).read_text()) == CONFIG


def test_unknown_logger_is_rejected_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match="unknown logger 'wandbb'"):
        MetricsLogger(str(tmp_path / "run"), ["wandbb"], CONFIG)
    assert not (tmp_path / "run").exists()


def test_tensorboard_values_land(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    log_steps(tmp_path, ["tensorboard"])
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    for key in ("train/loss", "eval/greedy_accuracy"):
        got = {e.step: e.value for e in events.Scalars(key)}
        assert got == pytest.approx({s: row[key] for s, row in EXPECTED.items()})


@pytest.mark.skipif(importlib.util.find_spec("wandb") is None, reason="wandb not installed (extra: loggers)")
def test_wandb_offline_values_land(tmp_path, monkeypatch):
    from wandb.proto import wandb_internal_pb2

    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_SILENT", "true")
    log_steps(tmp_path, ["wandb"])
    (run_file,) = glob.glob(str(tmp_path / "wandb" / "offline-run-*" / "run-*.wandb"))
    records = wait_for_records(run_file, wandb_internal_pb2.Record, last="exit")
    got, config = {}, {}
    for record in records:
        kind = record.WhichOneof("record_type")
        if kind == "history":
            items = {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in record.history.item}
            step = items.pop("_step")
            got[step] = {k: v for k, v in items.items() if not k.startswith("_")}
        elif kind in ("run", "config"):  # the config goes out with the run record (and any updates)
            updates = record.run.config.update if kind == "run" else record.config.update
            config.update({item.key: json.loads(item.value_json) for item in updates})
    assert got == EXPECTED  # every value is exact in float32
    assert config["lr"] == CONFIG["lr"] and config["model"] == CONFIG["model"]


@pytest.mark.skipif(importlib.util.find_spec("swanlab") is None, reason="swanlab not installed (extra: loggers)")
def test_swanlab_local_values_land(tmp_path, monkeypatch):
    from swanlab.proto.swanlab.record.v1.record_pb2 import Record

    monkeypatch.delenv("SWANLAB_MODE", raising=False)
    log_steps(tmp_path, ["swanlab"])
    (run_file,) = glob.glob(str(tmp_path / "swanlab" / "run-*" / "run-*.swanlab"))
    got: dict[int, dict] = {}
    for record in wait_for_records(run_file, Record, last="finish"):
        if record.WhichOneof("record_type") == "scalar":
            got.setdefault(record.scalar.step, {})[record.scalar.key] = record.scalar.value.number
    assert got == EXPECTED  # every value is exact in float32
    config_yaml = glob.glob(str(tmp_path / "swanlab" / "run-*" / "files" / "config.yaml"))
    assert config_yaml and "lr" in open(config_yaml[0]).read()
    assert not glob.glob(str(tmp_path / "run-*"))  # the run lives under swanlab/, not loose in output_dir


def write_rows(path, steps, tail=""):
    with open(path, "w") as handle:
        handle.writelines(json.dumps({"step": s, "train/loss": float(s)}) + "\n" for s in steps)
        handle.write(tail)


def test_a_row_cut_off_mid_write_is_dropped_on_resume(tmp_path, capsys):
    """A run killed while writing its last row leaves half a line; resuming drops it with a warning."""
    write_rows(tmp_path / "metrics.jsonl", [1, 2, 3, 4], tail='{"step": 5, "train/lo')
    assert [r["step"] for r in read_metrics(str(tmp_path / "metrics.jsonl"))] == [1, 2, 3, 4]
    assert "metrics.jsonl line 5 was cut off mid-write" in capsys.readouterr().err
    logger = MetricsLogger(str(tmp_path), [], CONFIG, start_step=3)
    logger.log({"train/loss": 0.5}, step=4)
    logger.close()
    assert [(r["step"], r["train/loss"]) for r in read_metrics(str(tmp_path / "metrics.jsonl"))] == [
        (1, 1.0), (2, 2.0), (3, 3.0), (4, 0.5)]


def test_a_damaged_row_before_the_last_is_named_with_its_line(tmp_path):
    from infinirl.config import ConfigError

    path = tmp_path / "metrics.jsonl"
    write_rows(path, [1, 2, 3])
    lines = path.read_text().splitlines(keepends=True)
    path.write_text(lines[0] + '{"step": 2, "train\n' + lines[2])
    with pytest.raises(ConfigError, match=r"metrics.jsonl line 2 is not a JSON row .*repair or delete that line"):
        MetricsLogger(str(tmp_path), [], CONFIG, start_step=3)
    path.write_text(lines[0] + "[2]\n" + lines[2])
    with pytest.raises(ConfigError, match=r"metrics.jsonl line 2 is not a JSON object"):
        read_metrics(str(path))


def test_tensorboard_after_resume_shows_each_step_once(tmp_path):
    """A run checkpointed at step 3 logged steps 4 and 5 before it crashed; the resumed run logs
    4 to 6 again. TensorBoard shows steps 1 to 6 once each, 4 and 5 with the resumed run's values."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    crashed = MetricsLogger(str(tmp_path), ["tensorboard"], CONFIG)
    for step in range(1, 6):
        crashed.log({"train/loss": float(step)}, step=step)
    crashed.close()
    resumed = MetricsLogger(str(tmp_path), ["tensorboard"], CONFIG, start_step=3)
    for step in range(4, 7):
        resumed.log({"train/loss": 10.0 * step}, step=step)
    resumed.close()
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    assert [(e.step, e.value) for e in events.Scalars("train/loss")] == [
        (1, 1.0), (2, 2.0), (3, 3.0), (4, 40.0), (5, 50.0), (6, 60.0)]


def _resumed_twice(tmp_path, loggers):
    """Log steps 1-2, then resume at step 2 and log step 3; the logger folder's stored run id."""
    first = MetricsLogger(str(tmp_path), loggers, CONFIG)
    for step in (1, 2):
        first.log({"train/loss": float(step)}, step=step)
    first.close()
    run_id = (tmp_path / loggers[0] / "run_id").read_text().strip()
    second = MetricsLogger(str(tmp_path), loggers, CONFIG, start_step=2)
    second.log({"train/loss": 3.0}, step=3)
    second.close()
    assert (tmp_path / loggers[0] / "run_id").read_text().strip() == run_id
    return run_id


@pytest.mark.skipif(importlib.util.find_spec("wandb") is None, reason="wandb not installed (extra: loggers)")
def test_wandb_resume_continues_the_same_run(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_SILENT", "true")
    run_id = _resumed_twice(tmp_path, ["wandb"])
    runs = glob.glob(str(tmp_path / "wandb" / "offline-run-*"))
    # Both folders carry the one run id, so `wandb sync` uploads them as one run; a folder opened in
    # the same second as the one before it gets a "-1" suffix after the id from newer wandb.
    assert len(runs) == 2 and all(re.search(rf"-{run_id}(-\d+)?$", r) for r in runs), runs


@pytest.mark.skipif(importlib.util.find_spec("swanlab") is None, reason="swanlab not installed (extra: loggers)")
def test_swanlab_resume_continues_the_same_run(tmp_path, monkeypatch):
    monkeypatch.delenv("SWANLAB_MODE", raising=False)
    run_id = _resumed_twice(tmp_path, ["swanlab"])
    runs = glob.glob(str(tmp_path / "swanlab" / "run-*" / "run-*.swanlab"))
    assert len(runs) == 2 and all(r.endswith(f"run-{run_id}.swanlab") for r in runs)
