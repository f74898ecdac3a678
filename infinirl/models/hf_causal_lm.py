"""Loading Hugging Face causal LMs, and building tiny ones for tests, without a model hub.

``load_causal_lm`` accepts a local HF model folder (safetensors, .bin or a single GGUF file), the
name of an embedded default model (``"smollm2-135m-instruct"``), or, where a hub is reachable, a
hub id. ``tiny_causal_lm`` makes a randomly initialised Llama with a real tokenizer, so engine
and trainer tests exercise real transformers code paths in milliseconds.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from transformers import AutoModelForCausalLM, AutoTokenizer, LlamaConfig, LlamaForCausalLM

from infinirl.engines.cpu_dtype import resolve_dtype
from infinirl.models import smollm2

# Named models we can produce with no hub access: name -> function returning a local folder.
EMBEDDED_MODELS = {smollm2.MODEL_NAME: smollm2.ensure_converted}

WEIGHT_SUFFIXES = (".safetensors", ".bin", ".gguf")


# ChatML, as SmolLM2 uses: lets tests of chat-templated prompts run on the tiny tokenizer.
CHATML_TEMPLATE = (
    "{% for message in messages %}"
    "{{ '<|im_start|>' + message['role'] + '\n' + message['content'] + '<|im_end|>\n' }}"
    "{% endfor %}"
    "{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif %}"
)


def find_weight_files(folder: Path) -> list[Path]:
    """The checkpoint files in ``folder`` (top level only, as transformers expects)."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.name.endswith(WEIGHT_SUFFIXES))


def resolve_model_source(path_or_name: str | os.PathLike) -> Path | str:
    """Local folder for ``path_or_name``; a string is returned unchanged only if it looks like a
    hub id (``org/name``) and is not a local path."""
    text = str(path_or_name)
    if text in EMBEDDED_MODELS:
        return EMBEDDED_MODELS[text]()
    path = Path(text).expanduser()
    if path.is_dir():
        return path
    if path.exists():
        raise NotADirectoryError(
            f"load_causal_lm: {path} is a file; pass the model folder that contains it"
        )
    if text.count("/") == 1 and not text.startswith((".", "/", "~")):
        return text  # hub id: transformers resolves (or fails offline with its own message)
    raise FileNotFoundError(
        f"load_causal_lm: {text!r} is neither a local model folder nor an embedded model "
        f"({', '.join(EMBEDDED_MODELS)}); download the model and pass its folder"
    )


def load_causal_lm(
    path_or_name: str | os.PathLike,
    *,
    dtype: torch.dtype | str = torch.float32,
    device: str | torch.device = "cpu",
):
    """Load ``(model, tokenizer)``: model in eval mode on ``device`` in ``dtype``.

    The tokenizer always has a pad id (the EOS id if the checkpoint defines none), because
    batched rollouts and training pad; padding is masked, so which id it is does not matter.
    """
    source = resolve_model_source(path_or_name)
    torch_dtype = resolve_dtype(dtype)
    extra: dict = {}
    if isinstance(source, Path):
        extra = _weights_kwargs(source)
    tokenizer = AutoTokenizer.from_pretrained(source, **extra)
    model = AutoModelForCausalLM.from_pretrained(source, dtype=torch_dtype, **extra)
    if tokenizer.pad_token_id is None and tokenizer.eos_token_id is not None:
        tokenizer.pad_token = tokenizer.eos_token
    return model.to(device).eval(), tokenizer


def _weights_kwargs(folder: Path) -> dict:
    """Check ``folder`` holds weights; return ``gguf_file=`` when a lone GGUF is all there is."""
    weights = find_weight_files(folder)
    if not weights:
        present = sorted(p.name for p in folder.iterdir())
        raise FileNotFoundError(
            f"load_causal_lm: no model weights in {folder} (looked for *.safetensors, *.bin, "
            f"*.gguf); it contains {present or 'nothing'}. Did the download finish?"
        )
    if all(p.suffix == ".gguf" for p in weights):
        if len(weights) > 1:
            raise ValueError(
                f"load_causal_lm: {folder} holds several GGUF files "
                f"{[p.name for p in weights]}; put the one you want in its own folder"
            )
        return {"gguf_file": weights[0].name}
    return {}


# --------------------------------------------------------------------------- tiny test models


def byte_level_tokenizer():
    """A 260-token byte-level tokenizer (256 bytes + 4 specials) built offline with ``tokenizers``.

    Character-level for ASCII and lossless for any text (no unknown tokens), which is all tests
    need. Specials mirror SmolLM2's ChatML ids: 0 ``<|endoftext|>``, 1 ``<|im_start|>``,
    2 ``<|im_end|>`` (EOS), plus 3 ``<|pad|>``.
    """
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    specials = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<|pad|>"]
    vocab = {tok: i for i, tok in enumerate(specials)}
    for char in sorted(pre_tokenizers.ByteLevel.alphabet()):
        vocab[char] = len(vocab)
    backend = Tokenizer(models.BPE(vocab=vocab, merges=[]))
    backend.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False)
    backend.decoder = decoders.ByteLevel()
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=backend,
        bos_token="<|im_start|>",
        eos_token="<|im_end|>",
        unk_token="<|endoftext|>",
        pad_token="<|pad|>",
    )
    tokenizer.chat_template = CHATML_TEMPLATE
    return tokenizer


def _tiny_tokenizer(kind: str):
    if kind == "byte":
        return byte_level_tokenizer()
    folder = smollm2.converted_dir()
    has_smollm2 = (folder / smollm2.PROVENANCE_FILE).is_file()
    if kind == "smollm2" or (kind == "auto" and has_smollm2):
        if not has_smollm2:
            raise FileNotFoundError(
                f"tiny_causal_lm(tokenizer='smollm2'): no converted SmolLM2 at {folder}; "
                f"run load_causal_lm('{smollm2.MODEL_NAME}') once, or use tokenizer='byte'"
            )
        return AutoTokenizer.from_pretrained(folder)
    if kind == "auto":
        return byte_level_tokenizer()
    raise ValueError(f"tiny_causal_lm: tokenizer={kind!r}; use 'auto', 'byte' or 'smollm2'")


def tiny_causal_lm(
    *,
    vocab_size: int | None = None,
    hidden: int = 64,
    layers: int = 2,
    heads: int = 4,
    kv_heads: int = 2,
    intermediate: int | None = None,
    max_positions: int = 1024,
    tokenizer: str = "auto",
    seed: int = 0,
    init_std: float = 0.2,
    dtype: torch.dtype | str = torch.float32,
):
    """A randomly initialised Llama (GQA, tied embeddings, like SmolLM2) and its tokenizer.

    ``tokenizer``: ``"byte"`` (the offline byte-level one, deterministic everywhere), ``"smollm2"``
    (the converted SmolLM2 tokenizer; must exist) or ``"auto"`` (SmolLM2's if converted, else
    byte). ``vocab_size`` defaults to the tokenizer's size and may not be smaller. ``seed`` fixes
    the initial weights. ``init_std`` is 10x HF's default so next-token distributions are far from
    uniform: log-prob, top-k/top-p and stop tests only discriminate on a peaked model.
    """
    tok = _tiny_tokenizer(tokenizer)
    vocab_size = vocab_size or len(tok)
    if vocab_size < len(tok):
        raise ValueError(
            f"tiny_causal_lm: vocab_size={vocab_size} is smaller than the tokenizer's "
            f"{len(tok)} tokens; omit vocab_size to use the tokenizer's size"
        )
    if hidden % heads or heads % kv_heads:
        raise ValueError(
            f"tiny_causal_lm: hidden={hidden}, heads={heads}, kv_heads={kv_heads}: hidden must "
            "divide by heads and heads by kv_heads"
        )
    config = LlamaConfig(
        vocab_size=vocab_size,
        hidden_size=hidden,
        intermediate_size=intermediate or 4 * hidden,
        num_hidden_layers=layers,
        num_attention_heads=heads,
        num_key_value_heads=kv_heads,
        max_position_embeddings=max_positions,
        tie_word_embeddings=True,
        initializer_range=init_std,
        bos_token_id=tok.bos_token_id,
        eos_token_id=tok.eos_token_id,
        pad_token_id=tok.pad_token_id,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = LlamaForCausalLM(config)
    return model.to(resolve_dtype(dtype)).eval(), tok
