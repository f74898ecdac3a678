"""Bad inputs to the OpenVLA-OFT loader and processor fail with one line, before anything runs."""

import json
import shutil

import pytest
import torch
from safetensors.torch import load_file, save_file

from infinirl.models.vla.openvla_oft import Platform
from tests.unit.models.vla_oft_fixtures import FOLDER, PI0_FOLDER, cameras, inputs, load, reference


def one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    return message


@pytest.fixture(scope="module")
def bundle():
    return load(head="l1")


@pytest.fixture()
def copy(tmp_path):
    target = tmp_path / "oft"
    shutil.copytree(FOLDER, target)
    return target


def test_folder_of_another_family_names_what_it_found():
    with pytest.raises(ValueError) as excinfo:
        load(PI0_FOLDER)
    assert "LeRobot 'pi0' policy" in one_line(excinfo) and "OpenVLAForActionPrediction" in str(excinfo.value)


def test_transformers_folder_of_another_model(copy):
    config = json.loads((copy / "config.json").read_text())
    config.update(architectures=["LlamaForCausalLM"], model_type="llama")
    (copy / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError) as excinfo:
        load(copy)
    assert "LlamaForCausalLM" in one_line(excinfo)


def test_unnorm_key_missing_or_unknown():
    with pytest.raises(ValueError) as excinfo:
        load(unnorm_key=None)
    assert "pass unnorm_key=" in one_line(excinfo) and "tiny_libero_no_noops" in str(excinfo.value)
    with pytest.raises(ValueError) as excinfo:
        load(unnorm_key="bridge_orig")
    assert "'bridge_orig' is not in" in one_line(excinfo)


def test_missing_statistics(copy):
    (copy / "dataset_statistics.json").unlink()
    with pytest.raises(ValueError) as excinfo:
        load(copy)
    assert "dataset_statistics.json" in one_line(excinfo)
    stats = json.loads((FOLDER / "dataset_statistics.json").read_text())
    del stats[inputs()["unnorm_key"]]["proprio"]["q99"]
    (copy / "dataset_statistics.json").write_text(json.dumps(stats))
    with pytest.raises(ValueError) as excinfo:
        load(copy)
    assert "proprio.q01/proprio.q99" in one_line(excinfo)


def test_statistics_of_another_platform():
    with pytest.raises(ValueError) as excinfo:
        load(platform="aloha")
    assert "platform" in one_line(excinfo)


def test_image_of_the_wrong_size_or_layout(bundle):
    big = [torch.zeros(2, 64, 64, 3, dtype=torch.uint8)] * 2
    with pytest.raises(ValueError) as excinfo:
        bundle.inputs(big, inputs()["tasks"], reference()["raw.proprio"])
    assert "64x64" in one_line(excinfo) and "resize=True" in str(excinfo.value)
    with pytest.raises(ValueError) as excinfo:
        bundle.inputs([torch.zeros(2, 32, 32, dtype=torch.uint8)] * 2, inputs()["tasks"], reference()["raw.proprio"])
    assert "[B, H, W, 3]" in one_line(excinfo)
    with pytest.raises(ValueError) as excinfo:
        bundle.inputs(cameras()[:1], inputs()["tasks"], reference()["raw.proprio"])
    assert "num_images=2" in one_line(excinfo)


def test_instruction_longer_than_the_context(bundle):
    with pytest.raises(ValueError) as excinfo:
        bundle.inputs(cameras(), ["pick up the red cube " * 40, "open"], reference()["raw.proprio"])
    assert "shorten it" in one_line(excinfo) and "256 positions" in str(excinfo.value)


def test_proprio_missing_or_of_the_wrong_width(bundle):
    with pytest.raises(ValueError) as excinfo:
        bundle.inputs(cameras(), inputs()["tasks"], None)
    assert "proprio=" in one_line(excinfo)
    with pytest.raises(ValueError) as excinfo:
        bundle.inputs(cameras(), inputs()["tasks"], torch.zeros(2, 5))
    assert "[B, 8]" in one_line(excinfo)


def _rewrite_shard(copy, edit):
    index = json.loads((copy / "model.safetensors.index.json").read_text())
    shard = copy / index["weight_map"]["projector.fc1.weight"]
    tensors = load_file(str(shard))
    edit(tensors)
    save_file(tensors, str(shard), metadata={"format": "pt"})


def test_unknown_missing_and_misshapen_weights(copy, tmp_path):
    _rewrite_shard(copy, lambda t: t.update({"projector.fc9.weight": torch.zeros(2)}))
    with pytest.raises(ValueError) as excinfo:
        load(copy)
    assert "'projector.fc9.weight' has no place" in one_line(excinfo)
    _rewrite_shard(copy, lambda t: (t.pop("projector.fc9.weight"), t.pop("projector.fc3.bias")))
    with pytest.raises(ValueError) as excinfo:
        load(copy)
    assert "no weights for 'projector.fc3.bias'" in one_line(excinfo)
    with pytest.raises(ValueError) as excinfo:
        load(vision=({"width": 16, "depth": 3, "num_heads": 2, "mlp_dim": 64, "patch_size": 8, "image_size": 32},
                     {"width": 24, "depth": 3, "num_heads": 2, "mlp_dim": 48, "patch_size": 8, "image_size": 32}))
    assert "has shape" in one_line(excinfo) and "expects" in str(excinfo.value)


def test_missing_shard_and_head_files(copy):
    (copy / "model-00003-of-00004.safetensors").unlink()
    with pytest.raises(FileNotFoundError) as excinfo:
        load(copy)
    assert "copy every shard" in one_line(excinfo)
    for path in copy.glob("action_head--*"):
        path.unlink()
    with pytest.raises(FileNotFoundError) as excinfo:
        load(copy, head="l1")
    assert "head='discrete'" in one_line(excinfo)


def test_head_file_of_the_wrong_component(copy):
    head = next(copy.glob("action_head--*"))
    projector = next(copy.glob("proprio_projector--*"))
    shutil.copy(projector, head)
    with pytest.raises(ValueError) as excinfo:
        load(copy, head="l1")
    assert "right file" in one_line(excinfo) or "no weights" in str(excinfo.value)


def test_unknown_platform_and_head():
    with pytest.raises(ValueError) as excinfo:
        load(platform="franka")
    assert "libero" in one_line(excinfo)
    with pytest.raises(ValueError) as excinfo:
        load(head="diffusion")
    assert "discrete" in one_line(excinfo)
    assert Platform(chunk_size=8, action_dim=7, proprio_dim=8).normalization == "bounds_q99"


def test_dinov2_blocks_of_either_transformers_layout_receive_the_published_weights():
    """Releases of transformers before its attention refactor nest DINOv2's attention (query/key/value,
    output.dense); the key map follows the layout of the model actually built."""
    from infinirl.models.vla.openvla_oft.checkpoint import block_layouts, vit_targets

    model = load(head="l1").model
    names = set(model.state_dict())
    assert block_layouts(model, names) == [spec.kind for spec in model.config.vision]
    nested = {"vision.featurizers.0.blocks.0.attention.attention.query.weight"}
    assert block_layouts(model, nested)[0] == "dinov2_nested"
    depth = model.config.vision[0].depth
    assert vit_targets("blocks.0.attn.qkv.weight", "p.", "dinov2_nested", depth) == [
        ("p.blocks.0.attention.attention.query.weight", 0), ("p.blocks.0.attention.attention.key.weight", 1),
        ("p.blocks.0.attention.attention.value.weight", 2)]
    assert vit_targets("blocks.0.attn.proj.bias", "p.", "dinov2_nested", depth) == [
        ("p.blocks.0.attention.output.dense.bias", None)]
    assert vit_targets("blocks.0.attn.proj.bias", "p.", "dinov2", depth) == [("p.blocks.0.attention.o_proj.bias", None)]
