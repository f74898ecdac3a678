"""The weights a vLLM engine expects every sync to send, read from the checkpoint as vLLM loads it
(no vLLM needed: small checkpoint folders written with safetensors / torch.save)."""

import json

import pytest
import torch
from safetensors.torch import save_file

from infinirl.engines.vllm_weights import checkpoint_weight_names, missing_weights

HF = {"model.embed_tokens.weight": torch.zeros(10, 4), "model.norm.weight": torch.zeros(4),
      "model.layers.0.mlp.up_proj.weight": torch.zeros(8, 4)}
SHAPES = {name: tuple(t.shape) for name, t in HF.items()}


def sharded(folder, extra_files=True):
    """An HF sharded checkpoint (index + two shards), with Mistral's consolidated.safetensors beside
    it: other names for the same weights, which vLLM skips (the index does not list the file)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = sorted(HF)
    shards = {"model-00001-of-00002.safetensors": names[:2], "model-00002-of-00002.safetensors": names[2:]}
    for file, members in shards.items():
        save_file({n: HF[n] for n in members}, str(folder / file))
    weight_map = {n: file for file, members in shards.items() for n in members}
    (folder / "model.safetensors.index.json").write_text(json.dumps({"metadata": {}, "weight_map": weight_map}))
    if extra_files:
        save_file({"tok_embeddings.weight": torch.zeros(10, 4), "norm.weight": torch.zeros(4)},
                  str(folder / "consolidated.safetensors"))
    return folder


def test_an_index_lists_the_weights_and_other_safetensors_files_are_left_out(tmp_path):
    assert checkpoint_weight_names(sharded(tmp_path / "m")) == SHAPES


def test_a_single_model_safetensors_is_read_alone(tmp_path):
    save_file(HF, str(tmp_path / "model.safetensors"))
    save_file({"tok_embeddings.weight": torch.zeros(10, 4)}, str(tmp_path / "consolidated.safetensors"))
    expected = checkpoint_weight_names(tmp_path)
    assert expected == SHAPES
    # every name the trainer sends is expected: a full sync misses nothing
    assert missing_weights(expected, set(HF)) == set()


def test_pytorch_bin_checkpoints_are_listed(tmp_path):
    single = tmp_path / "single"
    single.mkdir()
    torch.save(HF, single / "pytorch_model.bin")
    assert checkpoint_weight_names(single) == SHAPES
    split = tmp_path / "split"
    split.mkdir()
    torch.save({"model.norm.weight": HF["model.norm.weight"]}, split / "pytorch_model-00001-of-00002.bin")
    torch.save({n: t for n, t in HF.items() if n != "model.norm.weight"}, split / "pytorch_model-00002-of-00002.bin")
    weight_map = {n: f"pytorch_model-0000{1 if n == 'model.norm.weight' else 2}-of-00002.bin" for n in HF}
    (split / "pytorch_model.bin.index.json").write_text(json.dumps({"weight_map": weight_map}))
    assert checkpoint_weight_names(split) == SHAPES


def test_a_hub_id_is_read_from_the_hugging_face_cache(tmp_path):
    # The cache's layout: models--org--name/refs/main names the snapshot holding the files.
    repo = tmp_path / "hub" / "models--org--tiny"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("abc123")
    sharded(repo / "snapshots" / "abc123")
    assert checkpoint_weight_names("org/tiny", cache_dir=tmp_path / "hub") == SHAPES


@pytest.mark.parametrize("layout", ["empty", "consolidated only", "shard missing", "uncached hub id"])
def test_a_checkpoint_that_cannot_be_listed_is_an_error_naming_it(tmp_path, layout):
    source = tmp_path / "m"
    if layout == "empty":
        source.mkdir()
    elif layout == "consolidated only":
        source.mkdir()
        save_file({"tok_embeddings.weight": torch.zeros(10, 4)}, str(source / "consolidated.safetensors"))
    elif layout == "shard missing":
        sharded(source)
        (source / "model-00002-of-00002.safetensors").unlink()
    else:
        source = "org/not-downloaded"
    with pytest.raises(ValueError, match=rf"cannot list the weights of {source}.*"):
        checkpoint_weight_names(source, cache_dir=tmp_path / "hub")
