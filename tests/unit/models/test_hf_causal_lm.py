"""Model loading from local folders, and the offline tiny models that other tests build on."""

import pytest
import torch

from infinirl.models.hf_causal_lm import (
    byte_level_tokenizer,
    load_causal_lm,
    resolve_dtype,
    tiny_causal_lm,
)


def test_folder_without_weights_names_folder_and_contents(tmp_path):
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "tokenizer.json").write_text("{}")
    with pytest.raises(FileNotFoundError) as err:
        load_causal_lm(tmp_path)
    message = str(err.value)
    assert str(tmp_path) in message
    assert "config.json" in message and "tokenizer.json" in message
    assert "*.safetensors" in message


def test_unknown_name_and_file_paths_fail_clearly(tmp_path):
    with pytest.raises(FileNotFoundError, match="smollm2-135m-instruct"):
        load_causal_lm("no-such-model")
    weights_file = tmp_path / "model.safetensors"
    weights_file.write_bytes(b"")
    with pytest.raises(NotADirectoryError, match="model folder"):
        load_causal_lm(weights_file)


def test_save_and_load_round_trip_keeps_weights_tokenizer_and_dtype(tmp_path):
    model, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
    model.save_pretrained(tmp_path)
    tokenizer.save_pretrained(tmp_path)
    loaded, loaded_tok = load_causal_lm(tmp_path, dtype="float32")
    assert not loaded.training
    expected = model.state_dict()
    assert all(torch.equal(t, expected[k]) for k, t in loaded.state_dict().items())
    assert loaded.lm_head.weight is loaded.model.embed_tokens.weight  # tying survives
    text = "Hi <3, ünïcode!"
    assert loaded_tok(text).input_ids == tokenizer(text).input_ids
    assert loaded_tok.chat_template == tokenizer.chat_template
    half, _ = load_causal_lm(tmp_path, dtype="bf16")
    assert half.dtype == torch.bfloat16


def test_resolve_dtype_accepts_aliases_and_rejects_typos():
    assert resolve_dtype("bf16") is torch.bfloat16
    assert resolve_dtype(torch.float16) is torch.float16
    with pytest.raises(ValueError, match="bfloat61"):
        resolve_dtype("bfloat61")


def test_byte_level_tokenizer_is_lossless_and_chat_ready():
    tokenizer = byte_level_tokenizer()
    assert len(tokenizer) == 260
    assert (tokenizer.pad_token_id, tokenizer.bos_token_id, tokenizer.eos_token_id) == (3, 1, 2)
    text = "What is 2+3?\n  Ünïcödé ✓"
    ids = tokenizer(text).input_ids
    assert len(ids) == len(text.encode("utf-8"))  # one token per byte
    assert tokenizer.decode(ids) == text
    prompt = tokenizer.apply_chat_template(
        [{"role": "user", "content": "hi"}], add_generation_prompt=True, tokenize=False
    )
    assert prompt == "<|im_start|>user\nhi<|im_end|>\n<|im_start|>assistant\n"
    chat_ids = tokenizer.apply_chat_template(
        [{"role": "user", "content": "hi"}], add_generation_prompt=True, return_dict=False
    )
    assert chat_ids[0] == tokenizer.bos_token_id and tokenizer.eos_token_id in chat_ids


def test_tiny_causal_lm_is_seeded_and_validates_sizes():
    small = dict(tokenizer="byte", hidden=32, layers=1, heads=2, kv_heads=1)
    a, tokenizer = tiny_causal_lm(seed=0, **small)
    b, _ = tiny_causal_lm(seed=0, **small)
    c, _ = tiny_causal_lm(seed=1, **small)
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    assert not torch.equal(a.model.embed_tokens.weight, c.model.embed_tokens.weight)
    assert a.config.vocab_size == len(tokenizer) and a.config.num_hidden_layers == 1
    with pytest.raises(ValueError, match="vocab_size=10"):
        tiny_causal_lm(tokenizer="byte", vocab_size=10)
    with pytest.raises(ValueError, match="divide"):
        tiny_causal_lm(tokenizer="byte", hidden=30, heads=4)


def test_tiny_causal_lm_does_not_disturb_global_rng():
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    tiny_causal_lm(tokenizer="byte", hidden=32, layers=1, heads=2, kv_heads=1)
    assert torch.equal(torch.rand(3), expected)
