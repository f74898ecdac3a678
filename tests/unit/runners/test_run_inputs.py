"""What a run reads besides its config (its data files, what bfloat16 computes in on the host's CPU)
is recorded with each checkpoint and compared on resume before any worker starts: the real run loop
and the reasoning runner's config, with a flow that holds no state (no Ray)."""

from __future__ import annotations

import json
import os
import platform

import pytest

from infinirl.config import ConfigError, to_dataclass
from infinirl.runners.curves import Panel
from infinirl.runners.loop import LoopSpec, RunLoop
from infinirl.runners.reasoning_config import ReasoningConfig

ROWS = [{"question": f"{i}+1", "answer": str(i + 1)} for i in range(8)]


class StatelessFlow:
    spec = LoopSpec(name="inputs", title="inputs", headline="eval/score", panels=(Panel(title="x", y=("x",)),))

    def start(self, iteration: int) -> None:
        pass

    def step(self, iteration: int) -> dict:
        return {"x": float(iteration)}

    def evaluate(self) -> dict:
        return {"eval/score": 0.0}

    def save(self, folder: str) -> dict:
        return {}

    def load(self, folder: str, state: dict) -> None:
        pass

    def finish(self, output_dir: str) -> dict:
        return {}


def reasoning(tmp_path, iterations: int, **raw) -> ReasoningConfig:
    return to_dataclass(ReasoningConfig, {"output_dir": str(tmp_path / "run"), "iterations": iterations,
                                          "loggers": [], "eval": {"at_start": False}, **raw})


def run(cfg) -> dict:
    with RunLoop(cfg) as loop:
        return loop.run(StatelessFlow())


def write_rows(path, rows) -> None:
    path.write_text("".join(json.dumps(row) + "\n" for row in rows))


def test_a_data_file_with_other_rows_is_refused_on_resume_naming_the_file(tmp_path):
    data = tmp_path / "problems.jsonl"
    write_rows(data, ROWS)
    task = {"source": "dataset", "name": str(data), "verifier": "math", "eval_size": 2}
    run(reasoning(tmp_path, 1, task=task))
    write_rows(data, [{**row, "answer": row["answer"] + "0"} if i == 5 else row for i, row in enumerate(ROWS)])
    with pytest.raises(ConfigError, match=rf"resume: task.name {data} is not the file .*iter_000001 trained on "
                                          r"\(.* bytes, sha256 [0-9a-f]{12}\); .*restore it.* or start over "
                                          r"with resume=false") as error:
        run(reasoning(tmp_path, 2, task=task))
    assert "\n" not in str(error.value)
    write_rows(data, ROWS)  # the same rows again: resumes
    run(reasoning(tmp_path, 2, task=task))


def test_a_preset_read_from_another_data_dir_is_refused_on_resume(tmp_path, monkeypatch):
    """INFINIRL_DATA_DIR picks the preset's files: another folder with other rows is another dataset."""
    for name, rows in (("one", ROWS), ("two", ROWS[::-1])):
        folder = tmp_path / name / "gsm8k"
        folder.mkdir(parents=True)
        for split in ("train", "test"):
            write_rows(folder / f"{split}.jsonl", [{**r, "answer": f"x\n#### {r['answer']}"} for r in rows])
    task = {"source": "dataset", "name": "gsm8k", "eval_size": 2}
    monkeypatch.setenv("INFINIRL_DATA_DIR", str(tmp_path / "one"))
    run(reasoning(tmp_path, 1, task=task))
    monkeypatch.setenv("INFINIRL_DATA_DIR", str(tmp_path / "two"))
    with pytest.raises(ConfigError, match=r"task.name=gsm8k \(train split\) .*two/gsm8k/train.jsonl is not the file "
                                          r".*one/gsm8k/train.jsonl.*INFINIRL_DATA_DIR"):
        run(reasoning(tmp_path, 2, task=task))
    monkeypatch.setenv("INFINIRL_DATA_DIR", str(tmp_path / "one"))
    run(reasoning(tmp_path, 2, task=task))
    state = json.load(open(tmp_path / "run" / "checkpoints" / "iter_000002" / "runner_state.json"))
    assert set(state["inputs"]["data"]) == {"task.name=gsm8k (train split)", "task.name=gsm8k (test split)"}


@pytest.fixture
def cpu_without_native_bf16(monkeypatch):
    """A CPU without AVX512-BF16 or AMX (this one may have them): what the dtype resolver reads."""
    import torch

    from infinirl.engines.cpu_dtype import cpu_bf16_is_fast

    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("bf16 falls back to float32 on x86 CPUs only")

    def lacks(on: bool) -> None:
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: not on)
        monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: not on, raising=False)
        cpu_bf16_is_fast.cache_clear()

    yield lacks
    cpu_bf16_is_fast.cache_clear()


def test_bfloat16_computing_in_another_dtype_than_the_checkpoint_did_is_refused(tmp_path, monkeypatch,
                                                                                cpu_without_native_bf16):
    monkeypatch.delenv("INFINIRL_CPU_BF16", raising=False)
    cpu_without_native_bf16(True)
    run(reasoning(tmp_path, 1, actor={"param_dtype": "bfloat16"}))
    state = json.load(open(tmp_path / "run" / "checkpoints" / "iter_000001" / "runner_state.json"))
    assert state["inputs"]["bfloat16_on_cpu"] == {"computes_in": "float32", "keys": ["actor.param_dtype"]}
    monkeypatch.setenv("INFINIRL_CPU_BF16", "1")  # now bf16 stays bf16 on this CPU
    from infinirl.engines.cpu_dtype import cpu_bf16_is_fast

    cpu_bf16_is_fast.cache_clear()
    with pytest.raises(ConfigError, match=r"resume: bfloat16 \(actor.param_dtype\) computes in bfloat16 on this "
                                          r"host's CPU, in float32 when .*iter_000001 was written.*unset "
                                          r"INFINIRL_CPU_BF16.*resume=false"):
        run(reasoning(tmp_path, 2, actor={"param_dtype": "bfloat16"}))
    monkeypatch.delenv("INFINIRL_CPU_BF16")
    cpu_bf16_is_fast.cache_clear()
    run(reasoning(tmp_path, 2, actor={"param_dtype": "bfloat16"}))


def test_a_run_that_asks_for_no_bfloat16_records_no_dtype_and_older_checkpoints_resume(tmp_path):
    run(reasoning(tmp_path, 1))
    path = tmp_path / "run" / "checkpoints" / "iter_000001"
    state = json.load(open(path / "runner_state.json"))
    assert "bfloat16_on_cpu" not in state["inputs"]
    # a checkpoint written before inputs were recorded: nothing to compare
    del state["inputs"]
    (path / "runner_state.json").write_text(json.dumps(state))
    from infinirl.runners.checkpoints import MANIFEST_FILE, _manifest

    (path / MANIFEST_FILE).write_text(json.dumps(_manifest(str(path))))
    run(reasoning(tmp_path, 2))
    assert os.path.isdir(tmp_path / "run" / "checkpoints" / "iter_000002")


def test_a_run_on_gpus_records_no_cpu_dtype_so_moving_it_to_another_host_resumes(tmp_path, monkeypatch,
                                                                                 cpu_without_native_bf16):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    cpu_without_native_bf16(True)
    run(reasoning(tmp_path, 1, actor={"param_dtype": "bfloat16"}))
    state = json.load(open(tmp_path / "run" / "checkpoints" / "iter_000001" / "runner_state.json"))
    assert "bfloat16_on_cpu" not in state.get("inputs", {})
