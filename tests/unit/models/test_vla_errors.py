"""Bad inputs to the VLA loader and processor fail with one line naming the file/key and the fix."""

import json
import shutil

import pytest
import torch
from safetensors.torch import load_file, save_file

from infinirl.models.vla import PiZero, load_vla, read_vla_config
from infinirl.models.vla.checkpoint import map_checkpoint_keys, read_safetensors
from tests.unit.models.vla_fixtures import FIXTURES, architecture, load, raw_observation


def one_line(error) -> str:
    message = str(error.value)
    assert "\n" not in message, message
    return message


@pytest.fixture(scope="module")
def pi0():
    return load("pi0")


def copy_of(tmp_path, family="pi0"):
    folder = tmp_path / family
    shutil.copytree(FIXTURES / family, folder)
    return folder


def test_other_family_is_refused():
    with pytest.raises(ValueError) as error:
        read_vla_config(FIXTURES / "pi05", family="pi0", architecture=architecture())
    assert "'pi05' checkpoint, not 'pi0'" in one_line(error)


def test_hf_model_folder_is_refused(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"model_type": "gemma", "hidden_size": 8}))
    with pytest.raises(ValueError) as error:
        read_vla_config(tmp_path)
    message = one_line(error)
    assert "not a LeRobot policy config" in message and "'gemma'" in message


def test_other_lerobot_policy_is_refused(tmp_path):
    folder = copy_of(tmp_path)
    config = json.loads((folder / "config.json").read_text())
    config["type"] = "smolvla"
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError) as error:
        read_vla_config(folder)
    assert "'smolvla' policy" in one_line(error)


def test_missing_folder_files(tmp_path):
    with pytest.raises(FileNotFoundError) as error:
        read_vla_config(tmp_path)
    assert "no config.json" in one_line(error)
    folder = copy_of(tmp_path)
    (folder / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError) as error:
        load_vla(folder, architecture=architecture())
    assert "no model.safetensors" in one_line(error)


def test_missing_normalisation_stats(tmp_path):
    folder = copy_of(tmp_path)
    stats_file = next(folder.glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
    stats_file.unlink()
    with pytest.raises(FileNotFoundError) as error:
        load_vla(folder, architecture=architecture())
    message = one_line(error)
    assert stats_file.name in message and "stats=" in message


def test_incomplete_normalisation_stats_name_the_stat(tmp_path):
    folder = copy_of(tmp_path)
    stats_file = next(folder.glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
    stats = load_file(str(stats_file))
    del stats["observation.state.std"]
    save_file(stats, str(stats_file))
    with pytest.raises(ValueError) as error:
        load_vla(folder, architecture=architecture())
    message = one_line(error)
    assert "observation.state.std" in message and stats_file.name in message
    given = {"observation.state": {"mean": torch.zeros(5), "std": torch.ones(5)}}
    vla = load_vla(folder, architecture=architecture(), stats=given)
    assert torch.equal(vla.processor.state(torch.ones(1, 5))[:, :5], torch.ones(1, 5) / (1 + 1e-8))


def test_wrong_image_shapes(pi0):
    resolution = pi0.config.image_resolution[0]
    with pytest.raises(ValueError) as error:
        pi0.model.embed_images(torch.zeros(1, 3, resolution + 4, resolution + 4))
    assert f"[B, 3, {resolution}, {resolution}]" in one_line(error)
    observation = raw_observation("pi0")
    observation["observation.images.base_0_rgb"] = torch.zeros(2, 48, 48, 4)
    with pytest.raises(ValueError) as error:
        pi0.inputs(observation)
    assert "observation.images.base_0_rgb" in one_line(error)


def test_any_image_size_is_resized(pi0):
    observation = raw_observation("pi0")
    observation["observation.images.base_0_rgb"] = torch.randint(0, 255, (2, 20, 50, 3), dtype=torch.uint8)
    images = pi0.inputs(observation).images
    assert images[0].shape == (2, 3, *pi0.config.image_resolution)
    assert images[0].min() >= -1 and images[0].max() <= 1


def test_too_long_instruction(pi0):
    observation = raw_observation("pi0")
    observation["task"] = ["pick up the red cube and place it in the bowl and open the top drawer", "open"]
    with pytest.raises(ValueError) as error:
        pi0.inputs(observation)
    message = one_line(error)
    assert "tokenizer_max_length 16" in message and "pick up the red cube" in message


def test_no_tokenizer():
    vla = load("pi0", tokenizer=None)
    with pytest.raises(ValueError) as error:
        vla.inputs(raw_observation("pi0"))
    assert "tokenizer=" in one_line(error)


def test_wrong_state_width(pi0):
    observation = raw_observation("pi0")
    observation["observation.state"] = torch.zeros(2, 7)
    with pytest.raises(ValueError) as error:
        pi0.inputs(observation)
    assert "[B, 5]" in one_line(error)


def test_published_sizes_do_not_fit_a_tiny_checkpoint():
    """Without ``architecture=`` the variant names mean the published sizes: a shape error says so.
    (Checked on the key map alone: a gemma_2b model is too large to build in a unit test.)"""
    tensors = read_safetensors(FIXTURES / "pi0" / "model.safetensors")
    config = read_vla_config(FIXTURES / "pi0", architecture=architecture())
    model = PiZero(config)
    tensors["model.state_proj.weight"] = torch.zeros(3, 3)
    with pytest.raises(ValueError) as error:
        map_checkpoint_keys(tensors, model)
    message = one_line(error)
    assert "'state_proj.weight' has shape [3, 3]" in message and "architecture=" in message


def test_key_map_errors_and_aliases():
    tensors = read_safetensors(FIXTURES / "pi0" / "model.safetensors")
    model = PiZero(read_vla_config(FIXTURES / "pi0", architecture=architecture()))
    with pytest.raises(ValueError) as error:
        map_checkpoint_keys({**tensors, "model.extra_head.weight": torch.zeros(1)}, model)
    assert "'model.extra_head.weight' has no place in a 'pi0' model" in one_line(error)
    incomplete = {k: v for k, v in tensors.items() if "state_proj" not in k}
    with pytest.raises(ValueError) as error:
        map_checkpoint_keys(incomplete, model)
    assert "no weights for 'state_proj.bias' (and 1 more)" in one_line(error)
    # openpi's layout: no "model." prefix, an untied embedding, older time-MLP names.
    openpi = {k[len("model."):].replace("action_time_mlp", "time_mlp"): v for k, v in tensors.items()}
    embedding = openpi.pop("paligemma_with_expert.paligemma.lm_head.weight")
    openpi["paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight"] = embedding
    mapped = map_checkpoint_keys(openpi, model)
    assert torch.equal(mapped["vlm.embed_tokens.weight"], embedding)
    assert torch.equal(mapped["action_time_mlp_in.weight"], tensors["model.action_time_mlp_in.weight"])


def test_pi0_weights_refused_by_a_pi05_model():
    tensors = read_safetensors(FIXTURES / "pi0" / "model.safetensors")
    model = PiZero(read_vla_config(FIXTURES / "pi05", architecture=architecture()))
    with pytest.raises(ValueError) as error:
        map_checkpoint_keys(tensors, model)
    assert "has no place in a 'pi05' model" in one_line(error)
