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
                                          r"\(.* bytes, sha256 [0-9a-f]{12}; now .*\); .*restore it.* or start over "
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
                                          r".*trained on \(.*one/gsm8k/train.jsonl: "):
        run(reasoning(tmp_path, 2, task=task))
    monkeypatch.setenv("INFINIRL_DATA_DIR", str(tmp_path / "one"))
    run(reasoning(tmp_path, 2, task=task))
    state = json.load(open(tmp_path / "run" / "checkpoints" / "iter_000002" / "runner_state.json"))
    assert set(state["inputs"]["data"]) == {"task.name=gsm8k (train split)", "task.name=gsm8k (test split)"}


def sft(tmp_path, iterations: int, **raw):
    from infinirl.runners.sft_config import SFTConfig

    return to_dataclass(SFTConfig, {"output_dir": str(tmp_path / "run"), "iterations": iterations, "loggers": [],
                                    "eval": {"at_start": False},
                                    "optim": {"warmup_steps": 0, "lr_schedule": "constant"}, **raw})


def fake_folder(path, **files):
    for name, text in files.items():
        (path / name).parent.mkdir(parents=True, exist_ok=True)
        (path / name).write_text(text)
    return path


def test_a_folder_digest_covers_names_sizes_and_contents_but_not_unfinished_writes(tmp_path):
    from infinirl.runners.run_inputs import tree_digest

    folder = fake_folder(tmp_path / "ds", **{"meta/info.json": "{}", "meta/stats.json": "[1]", "data/a.bin": "xy"})
    first = tree_digest(folder)
    assert first["files"] == 3 and first["size"] == 7
    (folder / ".stats.json.a1b2.tmp").write_text("being written")  # utils.atomic's temporary file
    (folder / ".ds.tmp-x1").mkdir()
    (folder / ".ds.tmp-x1" / "big.bin").write_text("a dataset writer's unfinished folder")
    assert tree_digest(folder) == first
    (folder / "data" / "a.bin").rename(folder / "data" / "b.bin")  # same bytes under another name
    assert tree_digest(folder)["sha256"] != first["sha256"]
    (folder / "data" / "b.bin").rename(folder / "data" / "a.bin")
    (folder / "meta" / "stats.json").write_text("[2]")  # same size, other bytes
    changed = tree_digest(folder)
    assert changed["size"] == first["size"] and changed["sha256"] != first["sha256"]


def test_an_sft_dataset_or_initial_model_changed_on_disk_is_refused_on_resume(tmp_path):
    """The demonstrations' statistics and the initial model are read again on resume: another
    folder there is refused, naming the key and the folder, before anything is built."""
    data = fake_folder(tmp_path / "demos", **{"meta/stats.json": '{"action": {"mean": [0.0]}}'})
    init = fake_folder(tmp_path / "init", **{"config.json": "{}", "model.safetensors": "weights"})
    raw = {"data": {"path": str(data)}, "model": {"init": str(init)}}
    run(sft(tmp_path, 1, **raw))
    state = json.load(open(tmp_path / "run" / "checkpoints" / "iter_000001" / "runner_state.json"))
    assert set(state["inputs"]["data"]) == {"data.path", "model.init"}
    (data / "meta" / "stats.json").write_text('{"action": {"mean": [1.0]}}')
    with pytest.raises(ConfigError, match=rf"^resume: data.path {data} is not the folder .*iter_000001 trained on "
                                          r"\(.* bytes, sha256 [0-9a-f]{12}; now .*\); the restored state would go on "
                                          r"over other data; restore it, or start over with resume=false") as error:
        run(sft(tmp_path, 2, **raw))
    assert "\n" not in str(error.value)
    (data / "meta" / "stats.json").write_text('{"action": {"mean": [0.0]}}')
    (init / "model.safetensors").write_text("other weights")
    with pytest.raises(ConfigError, match=rf"^resume: model.init {init} is not the folder"):
        run(sft(tmp_path, 2, **raw))
    (init / "model.safetensors").write_text("weights")
    run(sft(tmp_path, 2, **raw))


def test_what_a_run_prepares_is_recorded_by_its_first_checkpoint(tmp_path):
    """A dataset the runner makes (SFT generates its demonstrations) before the inputs are recorded:
    the first checkpoint holds its digest, so a resume over another one is refused."""
    data = tmp_path / "demos"

    def generate():
        if not data.exists():
            fake_folder(data, **{"meta/info.json": "generated"})

    cfg = sft(tmp_path, 1, data={"path": str(data)})
    with RunLoop(cfg, prepare=generate) as loop:
        loop.run(StatelessFlow())
    state = json.load(open(tmp_path / "run" / "checkpoints" / "iter_000001" / "runner_state.json"))
    assert state["inputs"]["data"]["data.path"]["files"] == 1
    (data / "meta" / "info.json").write_text("generated again, differently")
    with pytest.raises(ConfigError, match=r"^resume: data.path .* is not the folder"):
        with RunLoop(sft(tmp_path, 2, data={"path": str(data)}), prepare=generate) as loop:
            loop.run(StatelessFlow())


def test_the_embodied_and_sac_runners_name_their_demonstrations_and_checkpoints():
    from infinirl.runners.embodied_config import EmbodiedConfig
    from infinirl.runners.sac_config import SACConfig

    vla = {"policy": "pi0_smollm2", "checkpoint": "runs/sft/policy"}
    sac = to_dataclass(SACConfig, {"env": {"name": "vla_noise:metaworld:reach-v3", "kwargs": {"vla": vla}}})
    assert sac.data_files() == {"env.kwargs.vla.checkpoint": "runs/sft/policy"}
    assert to_dataclass(SACConfig, {}).data_files() == {}
    embodied = to_dataclass(EmbodiedConfig, {"algorithm": {"bc": {"data": "data/demos"}},
                                             "policy": {"kwargs": {"checkpoint": "runs/sft/policy"}}})
    assert embodied.data_files() == {"algorithm.bc.data": "data/demos", "policy.kwargs.checkpoint": "runs/sft/policy"}
    assert to_dataclass(EmbodiedConfig, {}).data_files() == {}


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


def test_a_file_is_read_once_per_process_until_it_changes(tmp_path, monkeypatch):
    """Inputs are recorded with every checkpoint: an unchanged multi-GB checkpoint folder is not read
    again, but any write to a file is seen (its change time moves)."""
    from infinirl.runners import run_inputs as module

    data = tmp_path / "weights.bin"
    data.write_bytes(b"a" * 1000)
    reads = []
    real = module._read_sha256
    monkeypatch.setattr(module, "_read_sha256", lambda path: reads.append(path) or real(path))
    first = module.tree_digest(tmp_path)
    assert module.tree_digest(tmp_path) == first and len(reads) == 1
    with open(data, "r+b") as handle:  # same size, same bytes' count: the change time still moves
        handle.write(b"b")
    assert module.tree_digest(tmp_path)["sha256"] != first["sha256"] and len(reads) == 2
