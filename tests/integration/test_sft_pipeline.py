"""The SFT runner end to end: MetaWorld demonstrations generated into a LeRobotDataset, a tiny
pi0_smollm2 (SmolLM2's first layer) trained for 3 steps with a held-out evaluation in the env,
checkpoints, exact resume, and the final policy folder loading as the RL policy."""

import json

import pytest

pytest.importorskip("metaworld")
pytest.importorskip("pyarrow")

from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.models import smollm2  # noqa: E402
from infinirl.models.policies.base import build_policy  # noqa: E402
from infinirl.runners.sft import run  # noqa: E402
from infinirl.runners.sft_config import SFTConfig  # noqa: E402
from tests.integration.pins import check_pinned  # noqa: E402
from tests.integration.resume import killed_after_checkpoint  # noqa: E402

pytestmark = pytest.mark.skipif(
    smollm2.find_gguf() is None and not (smollm2.converted_dir() / smollm2.PROVENANCE_FILE).is_file(),
    reason=f"SmolLM2 not installed: {smollm2.INSTALL_HINT}")


def make_cfg(output_dir, data_path, **extra):
    raw = {
        "iterations": 3, "output_dir": str(output_dir), "save_every": 1, "loggers": [],
        "data": {"path": str(data_path), "generate": {"tasks": ["reach-v3"], "episodes_per_task": 1, "image_size": 16},
                 "augment_shift": 1},
        "model": {"language_layers": 1, "expert_width": 18, "expert_mlp_dim": 16, "vision_channels": [8, 8],
                  "chunk_size": 3, "n_action_steps": 2, "num_inference_steps": 2},
        "optim": {"batch_size": 4, "warmup_steps": 1},
        "eval": {"every": 2, "at_start": False, "episodes_per_task": 2, "num_envs": 2, "max_episode_steps": 6},
        **extra,
    }
    return to_dataclass(SFTConfig, raw)


def rows_of(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_sft_trains_evaluates_and_resumes_exactly(tmp_path):
    data = tmp_path / "demos"
    straight = run(make_cfg(tmp_path / "straight", data, device="auto"))  # the CPU here, a GPU where there is one
    assert (data / "meta" / "info.json").is_file()  # generated on first use
    rows = rows_of(tmp_path / "straight" / "metrics.jsonl")
    assert [r["step"] for r in rows] == [1, 2, 3]
    assert all(r["train/loss"] > 0 for r in rows)
    assert all(r["train/peak_memory_bytes"] > 0 for r in rows)
    assert "eval/success/reach-v3" in rows[1] and "eval/success_rate" in rows[2]
    assert straight["samples"] == 12
    check_pinned("sft", tmp_path / "straight", ["train/loss", "eval/success_rate"])

    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    resumed = run(make_cfg(tmp_path / "resumed", data))
    assert resumed["weights_sha256"] == straight["weights_sha256"]
    assert rows_of(tmp_path / "resumed" / "metrics.jsonl")[-1]["train/loss"] == rows[-1]["train/loss"]

    policy = build_policy("pi0_smollm2", checkpoint=straight["policy"], action_dim=4, chunk=2,
                          cameras={"rgb": "observation.images.corner"}, state_key="proprio")
    assert policy.vla.config.instructions == {"reach": "reach a goal position"}


def test_bad_data_and_tasks_fail_before_training(tmp_path):
    (tmp_path / "not_a_dataset").mkdir()
    with pytest.raises(ConfigError, match=r"^data.path: .*meta/info.json"):
        run(make_cfg(tmp_path / "out", tmp_path / "not_a_dataset"))
    assert not (tmp_path / "out").exists()
    with pytest.raises(ConfigError, match=r"^data.generate.tasks: unknown MetaWorld task 'nope-v3'"):
        run(make_cfg(tmp_path / "out", tmp_path / "new", data={"path": str(tmp_path / "new"),
                                                                "generate": {"tasks": ["nope-v3"]}}))
    assert not (tmp_path / "new").exists()
    with pytest.raises(ConfigError, match=r"^model.init=.*nope: no such folder; `infinirl train sft_vla_metaworld`"):
        run(make_cfg(tmp_path / "out", tmp_path / "new", model={"init": str(tmp_path / "nope")}))
    assert not (tmp_path / "new").exists()  # refused before any demonstration is generated


def test_a_device_that_is_not_there_is_one_line_before_the_data_is_read(tmp_path):
    import torch

    with pytest.raises(ConfigError, match=r"^device='gpu': use cpu, cuda, cuda:N or auto$"):
        make_cfg(tmp_path / "out", tmp_path / "data", device="gpu")
    missing = f"cuda:{torch.cuda.device_count()}"  # one past the last GPU (cuda:0 on a CPU-only machine)
    with pytest.raises(ConfigError, match=rf"^device='{missing}': this machine has \d+ CUDA device"):
        run(make_cfg(tmp_path / "out", tmp_path / "data", device=missing))
    assert not (tmp_path / "data").exists() and not (tmp_path / "out").exists()


def test_rejection_sampling_rounds_join_the_data_and_resume_exactly(tmp_path, monkeypatch):
    """RFT rounds with MetaWorld's scripted expert acting in place of the tiny VLA (which solves
    nothing in a few steps), so that every round keeps episodes: they are written as LeRobotDatasets,
    join the cloned frames, and a run resumed between rounds reads them back bit for bit."""
    from infinirl.data.lerobot_dataset import LeRobotDatasetReader
    from infinirl.runners.sft_rft import RejectionSampling
    from tests.unit.data.test_demos import ExpertChunkPolicy

    collect = RejectionSampling.collect
    monkeypatch.setattr(RejectionSampling, "collect",
                        lambda self, policy, vla: collect(self, ExpertChunkPolicy("reach-v3", chunk=2), vla))
    data = tmp_path / "demos"
    rft = {"every": 1, "episodes_per_task": 2, "num_envs": 2}
    straight = run(make_cfg(tmp_path / "straight", data, rft=rft))
    rows = rows_of(tmp_path / "straight" / "metrics.jsonl")
    assert [r.get("rft/round") for r in rows] == [None, 1, 2]  # a new model's first round waits `every` steps
    assert [r.get("rft/kept_episodes") for r in rows[1:]] == [2, 2]
    assert rows[1]["rft/success/reach-v3"] == 1.0 and rows[1]["rft/success_rate"] == 1.0
    base = rows[0]["train/frames"]
    assert rows[1]["train/frames"] == base + rows[1]["rft/kept_frames"]
    assert rows[2]["train/frames"] == rows[1]["train/frames"] + rows[2]["rft/kept_frames"]
    round_1 = LeRobotDatasetReader(tmp_path / "straight" / "rft" / "round_0001")
    assert round_1.num_episodes == 2 and round_1.tasks == ["reach a goal position"]

    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    resumed = run(make_cfg(tmp_path / "resumed", data, rft=rft))
    assert resumed["weights_sha256"] == straight["weights_sha256"]
    assert rows_of(tmp_path / "resumed" / "metrics.jsonl")[-1]["train/frames"] == rows[-1]["train/frames"]

    (tmp_path / "lost").mkdir()
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "lost" / "run", 2)
    import shutil

    shutil.rmtree(tmp_path / "lost" / "run" / "rft" / "round_0001")
    with pytest.raises(ConfigError, match=r"^resume: the RFT round .*round_0001 is missing: the checkpoint counts its "
                                          r"episodes .*restore it, or start the run again in a new output_dir"):
        run(make_cfg(tmp_path / "lost" / "run", data, rft=rft))
