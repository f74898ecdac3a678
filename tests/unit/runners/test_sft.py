"""The SFT runner's pieces on a tiny synthetic LeRobotDataset: action chunks and their padding,
the learning-rate schedule, the loss going down, and the config's one-line errors."""

import math

import numpy as np
import pytest
import torch

pytest.importorskip("pyarrow")

from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.data.demo_frames import DemoFrames, random_shift  # noqa: E402
from infinirl.data.lerobot_dataset import LeRobotDatasetReader, LeRobotDatasetWriter  # noqa: E402
from infinirl.runners.sft import learning_rate, task_instructions  # noqa: E402
from infinirl.runners.sft_config import SFTConfig  # noqa: E402
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla  # noqa: E402


def synthetic_dataset(root, episodes=(5, 3), tasks=("pick up the cube", "open the top drawer")) -> LeRobotDatasetReader:
    """Episodes whose action is a fixed function of the state; the image brightness encodes the task."""
    features = {"observation.state": {"dtype": "float32", "shape": (4,), "names": None},
                "action": {"dtype": "float32", "shape": (4,), "names": None},
                CAMERA: {"dtype": "video", "shape": (16, 16, 3), "names": ["height", "width", "channels"]}}
    rng = np.random.default_rng(0)
    with LeRobotDatasetWriter(root, fps=10, features=features) as writer:
        for number, length in enumerate(episodes):
            state = rng.normal(size=(length, 4)).astype(np.float32)
            frames = {"observation.state": state, "action": np.tanh(state[:, ::-1] + number).astype(np.float32),
                      CAMERA: np.full((length, 16, 16, 3), 60 + 120 * number, dtype=np.uint8)}
            writer.add_episode(frames, task=tasks[number])
    return LeRobotDatasetReader(root)


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return DemoFrames.read(synthetic_dataset(tmp_path_factory.mktemp("data") / "ds"))


def test_chunks_stop_at_the_episode_end(demos):
    assert len(demos) == 8 and demos.image_size == 16 and demos.camera_key == CAMERA
    observation, actions, valid = demos.batch(torch.tensor([0, 3, 4, 5]), chunk=3)
    assert valid.tolist() == [[True, True, True], [True, True, False], [True, False, False], [True, True, True]]
    assert torch.equal(actions[1], demos.action[[3, 4, 4]])  # the last action repeated, masked
    assert torch.equal(actions[3], demos.action[5:8])
    assert observation["task"] == ["pick up the cube"] * 3 + ["open the top drawer"]
    assert observation[CAMERA].shape == (4, 3, 16, 16) and observation[CAMERA].max() <= 1.0


def test_normalisation_stats_floor_the_std(demos):
    stats = demos.normalization_stats(min_std=10.0)
    assert torch.equal(stats["action"]["std"], torch.full((4,), 10.0))
    assert torch.allclose(stats["observation.state"]["mean"],
                          torch.as_tensor(demos.state.double().mean(0), dtype=torch.float32), atol=1e-5)


def test_random_shift_moves_whole_images():
    image = torch.arange(2 * 3 * 8 * 8, dtype=torch.float32).reshape(2, 3, 8, 8)
    torch.manual_seed(0)
    shifted = random_shift(image, 2)
    assert shifted.shape == image.shape
    # every output pixel comes from the padded input: interior pixels keep their horizontal neighbours' step
    assert torch.all(torch.isin(shifted[..., 1:] - shifted[..., :-1], torch.tensor([0.0, 1.0])))


def test_sft_loss_decreases_in_a_few_steps(demos):
    vla = tiny_vla(seed=1)
    vla.train()
    optimizer = torch.optim.AdamW(vla.model.parameters(), lr=3e-3)
    torch.manual_seed(0)
    indices = torch.arange(len(demos))
    observation, actions, valid = demos.batch(indices, chunk=vla.config.chunk_size)
    noise = torch.randn(len(indices), vla.config.chunk_size, 4)
    time = torch.linspace(0.1, 0.9, len(indices))

    def loss():
        return vla.loss(observation, actions, noise=noise, time=time, action_mask=valid)

    first = loss()
    for _ in range(8):
        optimizer.zero_grad()
        loss().backward()
        optimizer.step()
    assert loss().item() < 0.7 * first.item()


def test_learning_rate_schedule():
    cfg = to_dataclass(SFTConfig, {"iterations": 12, "optim": {"lr": 1.0, "warmup_steps": 1, "min_lr_ratio": 0.1}})
    assert learning_rate(0, cfg) == 1.0  # the warm-up's only step
    assert learning_rate(1, cfg) == 1.0 and math.isclose(learning_rate(11, cfg), 0.1)
    assert math.isclose(learning_rate(6, cfg), 0.55)  # half-way down the cosine
    constant = to_dataclass(SFTConfig, {"iterations": 11, "optim": {"lr": 1.0, "warmup_steps": 4,
                                                                     "lr_schedule": "constant"}})
    assert [learning_rate(i, constant) for i in (0, 3, 10)] == [0.25, 1.0, 1.0]


def test_eval_tasks_need_an_instruction_in_the_dataset():
    found = task_instructions(["reach-v3"], ["reach a goal position", "push the puck to a goal"])
    assert found == {"reach-v3": ("reach", "reach a goal position")}
    assert task_instructions(["reach-v3"], ["reach"]) == {"reach-v3": ("reach", "reach")}
    with pytest.raises(ConfigError, match=r"^eval.tasks: 'push-v3' has no instruction in the dataset"):
        task_instructions(["push-v3"], ["reach a goal position"])


@pytest.mark.parametrize("raw, message", [
    ({"model": {"n_action_steps": 9, "chunk_size": 8}}, "model.n_action_steps=9 must be <= model.chunk_size=8"),
    ({"model": {"expert_width": 100}}, "model.expert_width=100 must be a multiple of 18"),
    ({"optim": {"betas": [0.9]}}, "optim.betas=[0.9]: give two numbers"),
    ({"iterations": 10, "optim": {"warmup_steps": 10}}, "optim.warmup_steps=10 must be below iterations=10"),
])
def test_config_errors_name_the_key(raw, message):
    with pytest.raises(ConfigError) as error:
        to_dataclass(SFTConfig, raw)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_extended_frames_join_episodes_and_tasks_by_wording(demos, tmp_path):
    other = DemoFrames.read(synthetic_dataset(tmp_path / "other", episodes=(2, 4)))
    other.tasks = ["open the top drawer", "wipe the table"]  # one shared task, one new, in another order
    joined = demos.extended(other)
    assert len(joined) == 14 and joined.tasks == ["pick up the cube", "open the top drawer", "wipe the table"]
    assert joined.task_index[8:].tolist() == [1, 1, 2, 2, 2, 2]
    assert joined.episode_end.tolist() == [5] * 5 + [8] * 3 + [10] * 2 + [14] * 4
    _, actions, valid = joined.batch(torch.tensor([9]), chunk=3)
    assert valid.tolist() == [[True, False, False]]  # the chunk stops at the joined episode's end
    assert torch.equal(actions[0, 0], other.action[1])
    assert joined.stats is demos.stats
    other.camera_key = "observation.images.wrist"
    with pytest.raises(ValueError, match="cannot join frames of observation.images.wrist"):
        demos.extended(other)


def test_rft_round_seeds_are_distinct_repeatable_and_never_held_out():
    from infinirl.runners.sft_rft import round_seeds
    from infinirl.runners.sim_config import eval_seeds

    seeds = [round_seeds(0, r, t, 50) for r in (1, 2) for t in (0, 1)]
    flat = [s for group in seeds for s in group]
    assert len(set(flat)) == len(flat)
    assert round_seeds(0, 2, 1, 50) == seeds[3] and round_seeds(1, 2, 1, 50) != seeds[3]
    assert max(flat) < min(eval_seeds(0, 1))


def test_rft_rounds_are_due_every_n_steps_and_first_with_an_initial_policy():
    from infinirl.runners.sft_rft import RejectionSampling

    def due(**model):
        cfg = to_dataclass(SFTConfig, {"rft": {"every": 3}, "model": model})
        return [i for i in range(10) if RejectionSampling(cfg, {}, CAMERA, 16).due(i)]

    assert due() == [3, 6, 9]
    assert due(init="runs/sft/policy") == [0, 3, 6, 9]
    off = RejectionSampling(to_dataclass(SFTConfig, {}), {}, CAMERA, 16)
    assert not off.enabled and not any(off.due(i) for i in range(10))


def test_resume_refuses_a_new_length_under_the_cosine_schedule(tmp_path):
    from infinirl.config import to_plain
    from infinirl.runners.loop import RunLoop

    def sft(**raw) -> SFTConfig:
        return to_dataclass(SFTConfig, {"output_dir": str(tmp_path / "run"), "optim": {"warmup_steps": 1}, **raw})

    recorded = to_plain(sft(iterations=4))
    with pytest.raises(ConfigError, match=r"\(iterations: 4 -> 8\).*half-apply them \(optim.lr_schedule=cosine "
                                          r"decays over iterations; .*optim.lr_schedule=constant\)") as error:
        RunLoop(sft(iterations=8))._check_config("ckpt", recorded, 2)
    assert "\n" not in str(error.value)
    constant = {"warmup_steps": 1, "lr_schedule": "constant"}
    RunLoop(sft(iterations=8, optim=constant))._check_config("ckpt", to_plain(sft(iterations=4, optim=constant)), 2)


def test_resume_refuses_new_eval_tasks_only_when_they_are_also_the_rft_tasks(tmp_path):
    from infinirl.config import to_plain
    from infinirl.runners.loop import RunLoop

    def sft(tasks, **raw) -> SFTConfig:
        return to_dataclass(SFTConfig, {"output_dir": str(tmp_path / "run"), "eval": {"tasks": tasks}, **raw})

    rft = {"rft": {"every": 5}}
    with pytest.raises(ConfigError, match=r"eval.tasks: \['reach-v3'\] -> \['reach-v3', 'push-v3'\].*with "
                                          r"rft.every > 0, eval.tasks also names the tasks the RFT rounds collect in"):
        RunLoop(sft(["reach-v3", "push-v3"], **rft))._check_config("ckpt", to_plain(sft(["reach-v3"], **rft)), 2)
    # Without RFT they are only evaluated: the change applies.
    RunLoop(sft(["reach-v3", "push-v3"]))._check_config("ckpt", to_plain(sft(["reach-v3"])), 2)


def test_optimizer_state_saved_on_a_gpu_loads_on_a_cpu_only_machine(tmp_path, monkeypatch):
    """A checkpoint written on a GPU tags its tensors' storages cuda:0; ``device`` may change on
    resume, so the optimizer state must load where there is no GPU."""
    from infinirl.runners.sft import load_optimizer_state

    weight = torch.nn.Parameter(torch.ones(3))
    optimizer = torch.optim.AdamW([weight], lr=0.1)
    weight.sum().backward()
    optimizer.step()
    with monkeypatch.context() as patch:  # written as a GPU run writes it
        patch.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
        torch.save(optimizer.state_dict(), tmp_path / "optimizer.pt")
    restored = torch.optim.AdamW([torch.nn.Parameter(torch.ones(3))], lr=0.1)
    load_optimizer_state(restored, str(tmp_path / "optimizer.pt"))
    state = next(iter(restored.state.values()))
    assert state["exp_avg"].device.type == "cpu"
    assert torch.equal(state["exp_avg"], next(iter(optimizer.state.values()))["exp_avg"])


TINY_MODEL = {"language_layers": 1, "expert_width": 18, "expert_mlp_dim": 16, "vision_channels": [8, 8],
              "chunk_size": 3, "n_action_steps": 2, "num_inference_steps": 2}


@pytest.fixture(scope="module")
def saved_policy(demos, tmp_path_factory):
    from infinirl.models.vla.save import save_vla
    from infinirl.runners.sft import build_model

    vla = build_model(to_dataclass(SFTConfig, {"model": TINY_MODEL}), demos, {})
    return save_vla(vla, tmp_path_factory.mktemp("init") / "policy")


@pytest.mark.parametrize("model, frames, message", [
    ({"n_action_steps": 4}, {}, r"^model.n_action_steps=4 exceeds the chunk of model.init=.* \(3 actions per "
                                r"decision\); set model.n_action_steps <= 3$"),
    ({}, {"state": 3}, r"^data.path: the dataset's observation.state has 3 dimensions but model.init=.* was trained "
                       r"on 4; clone from demonstrations of the same robot"),
    ({}, {"action": 2}, r"^data.path: the dataset's action has 2 dimensions but model.init=.* was trained on 4"),
    ({}, {"camera_key": "observation.images.wrist"},
     r"^data.camera_key: the dataset's camera 'observation.images.wrist' is not one model.init=.* reads"),
])
def test_an_initial_model_that_does_not_fit_is_a_one_line_error(demos, saved_policy, model, frames, message):
    from dataclasses import replace

    from infinirl.runners.sft import build_model

    def cfg(**model) -> SFTConfig:  # model.chunk_size (8 by default) is a new model's, not checked against
        return to_dataclass(SFTConfig, {"model": {"init": str(saved_policy), "n_action_steps": 3, **model}})

    changed = {key: (getattr(demos, key)[:, :size] if isinstance(size, int) else size) for key, size in frames.items()}
    with pytest.raises(ConfigError, match=message):
        build_model(cfg(**model), replace(demos, **changed), {})
    assert build_model(cfg(), demos, {}).config.chunk_size == 3


def test_a_resumed_flow_normalises_with_the_statistics_of_its_checkpoint(demos, tmp_path):
    """The model is built with the statistics of data.path (or model.init) as they are now; loading a
    checkpoint puts back those it trained with, with its weights."""
    from dataclasses import replace

    from infinirl.runners.sft import SFTFlow

    cfg = to_dataclass(SFTConfig, {"output_dir": str(tmp_path / "run"), "model": TINY_MODEL})
    first = SFTFlow(cfg, demos, {})
    (tmp_path / "ckpt").mkdir()
    state = first.save(str(tmp_path / "ckpt"))
    moved = {key: {name: value + 1.0 for name, value in item.items()} for key, item in demos.stats.items()}
    resumed = SFTFlow(cfg, replace(demos, stats=moved), {})

    def stats(flow):
        processor = flow.vla.processor
        output = {f"out.{key}": value for key, value in processor.output_norm.state_dict().items()}
        return {**processor.input_norm.state_dict(), **output}

    assert any(not torch.equal(stats(resumed)[key], value) for key, value in stats(first).items())
    resumed.load(str(tmp_path / "ckpt"), state)
    assert all(torch.equal(stats(resumed)[key], value) for key, value in stats(first).items())
    first.close()
    resumed.close()


MT_TASKS = ("reach a goal position", "push the puck to a goal")
"""The natural instructions of reach-v3 and push-v3 (the dataset's wording of them)."""


@pytest.fixture(scope="module")
def metaworld_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("mw") / "ds"
    synthetic_dataset(root, tasks=MT_TASKS)
    return root


def sft_cfg(path, **raw) -> SFTConfig:
    return to_dataclass(SFTConfig, {"data": {"path": str(path)}, "eval": {"tasks": ["reach-v3", "push-v3"]}, **raw})


def copied(data, tmp_path):
    import shutil

    return shutil.copytree(data, tmp_path / "copy")


def test_benchmark_names_resolve_before_anything_is_generated(tmp_path):
    """data.generate.tasks=[MT10] (documented) evaluates MT10's tasks, instead of looking for an
    instruction for 'MT10' once the demonstrations exist; a bad name is one line naming its key."""
    pytest.importorskip("metaworld")
    from infinirl.runners.sft import preflight

    absent = tmp_path / "absent"
    tasks = preflight(to_dataclass(SFTConfig, {"data": {"path": str(absent), "generate": {"tasks": ["MT10"]}}}))
    assert len(tasks) == 10 and tasks[0] == "reach-v3"
    with pytest.raises(ConfigError, match=r"^eval.tasks: unknown MetaWorld task 'nope-v3'"):
        preflight(to_dataclass(SFTConfig, {"data": {"path": str(absent)}, "eval": {"tasks": ["reach-v3", "nope-v3"]}}))
    with pytest.raises(ConfigError, match=r"^data.generate.tasks: unknown MetaWorld task 'MT11'"):
        preflight(to_dataclass(SFTConfig, {"data": {"path": str(absent), "generate": {"tasks": ["MT11"]}}}))
    with pytest.raises(ConfigError, match=r"^eval.tasks: 'push-v3' is not among data.generate.tasks \(reach-v3\)"):
        preflight(to_dataclass(SFTConfig, {"data": {"path": str(absent), "generate": {"tasks": ["reach-v3"]}},
                                           "eval": {"tasks": ["push-v3"]}}))
    assert not absent.exists()


def test_preflight_reads_the_dataset_metadata_and_the_initial_model_without_weights(metaworld_data, saved_policy,
                                                                                    tmp_path):
    pytest.importorskip("metaworld")
    from infinirl.runners.sft import preflight

    assert preflight(sft_cfg(metaworld_data)) == ["reach-v3", "push-v3"]
    init = {"init": str(saved_policy), "n_action_steps": 3}
    assert preflight(sft_cfg(metaworld_data, model=init)) == ["reach-v3", "push-v3"]
    for raw, message in (
            ({"eval": {"tasks": ["drawer-close-v3"]}}, r"^eval.tasks: 'drawer-close-v3' has no instruction in the "
                                                       r"dataset"),
            ({"data": {"path": str(metaworld_data), "camera_key": "observation.images.wrist"}},
             r"^data.camera_key='observation.images.wrist': the dataset at .* has cameras"),
            ({"model": {**init, "n_action_steps": 4}}, r"^model.n_action_steps=4 exceeds the chunk of model.init"),
            ({"model": {"init": str(tmp_path / "nope")}}, r"^model.init=.*nope: no such folder")):
        with pytest.raises(ConfigError, match=message) as error:
            preflight(sft_cfg(metaworld_data, **raw))
        assert "\n" not in str(error.value)


def test_corrupt_statistics_and_task_indices_are_one_line_errors(metaworld_data, tmp_path):
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    pytest.importorskip("metaworld")
    from infinirl.runners.sft import preflight

    data = copied(metaworld_data, tmp_path)
    stats_file = data / "meta" / "stats.json"
    saved = stats_file.read_text()
    stats_file.write_text(saved[: len(saved) // 2])  # cut off mid-write
    with pytest.raises(ConfigError, match=r"^data.path: .*meta/stats.json is not a JSON object .*re-create it"):
        preflight(sft_cfg(data))
    stats = json.loads(saved)
    stats["action"]["mean"] = stats["action"]["mean"][:3]
    stats_file.write_text(json.dumps(stats))
    with pytest.raises(ConfigError, match=r"^data.path: .*stats.json gives action.mean shape \(3,\), but the "
                                          r"feature's shape is \(4,\)"):
        preflight(sft_cfg(data))
    stats_file.write_text(saved)
    frames = next((data / "data").glob("*/*.parquet"))
    table = pq.read_table(frames)
    column = table.schema.get_field_index("task_index")
    pq.write_table(table.set_column(column, "task_index", pa.array([7] * table.num_rows, pa.int64())), frames)
    with pytest.raises(ConfigError, match=r"^data.path: .*a frame has task_index 7, but meta/tasks.parquet lists 2 "
                                          r"tasks"):
        preflight(sft_cfg(data))


def test_a_video_that_does_not_decode_is_a_one_line_error(metaworld_data, tmp_path):
    from infinirl.runners.sft import open_dataset, read_demos

    data = copied(metaworld_data, tmp_path)
    video = next((data / "videos").rglob("*.mp4"))
    video.write_bytes(video.read_bytes()[:200])  # truncated
    with pytest.raises(ConfigError, match=r"^data.path: cannot decode video .*\.mp4") as error:
        read_demos(open_dataset(sft_cfg(data)), None)
    assert "\n" not in str(error.value)


def test_a_corrupt_initial_model_is_a_one_line_error(metaworld_data, saved_policy, demos, tmp_path):
    import shutil

    pytest.importorskip("metaworld")
    from infinirl.runners.sft import build_model, preflight

    init = shutil.copytree(saved_policy, tmp_path / "init")
    weights = init / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-100])  # truncated
    cfg = sft_cfg(metaworld_data, model={"init": str(init), "n_action_steps": 3})
    with pytest.raises(ConfigError, match=r"^model.init: .*model.safetensors is not a readable safetensors file"):
        preflight(cfg)
    with pytest.raises(ConfigError, match=r"^model.init: .*incomplete metadata"):
        build_model(cfg, demos, {})


def test_validate_runs_the_sft_preflight(tmp_path, capsys):
    pytest.importorskip("metaworld")
    from infinirl.cli import main

    data = f"data.path={tmp_path / 'absent'}"
    assert main(["validate", "sft_vla_metaworld", data]) == 0
    assert main(["validate", "sft_vla_metaworld", data, "data.generate.tasks=[MT10]"]) == 0
    assert main(["validate", "sft_vla_metaworld", data, "data.generate.tasks=[reach-v3]",
                 "eval.tasks=[push-v3]"]) == 2
    assert capsys.readouterr().err.startswith("infinirl: config error: eval.tasks: 'push-v3' is not among")
    assert main(["validate", "sft_vla_metaworld", data, f"model.init={tmp_path / 'none'}"]) == 2
    assert "model.init=" in capsys.readouterr().err
    assert not (tmp_path / "absent").exists()
