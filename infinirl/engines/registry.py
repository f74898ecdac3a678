"""Rollout (inference) engines by name, so ``rollout.engine: vllm`` is configuration, not code.

Each entry is a factory ``(model, dtype, device, max_batch_size, options) -> InferenceEngine``.
Factories import their engine lazily: the vLLM entry must not import vLLM in a process that only
ever uses the transformers engine (vLLM is an optional extra with its own pins).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from infinirl.engines.base import InferenceEngine
from infinirl.registry import Registry

EngineFactory = Callable[[str, str, str, int, dict[str, Any]], InferenceEngine]

ROLLOUT_ENGINES: Registry[EngineFactory] = Registry("rollout engine", entry_point_group="infinirl.rollout_engines")


@ROLLOUT_ENGINES.register("hf")
def _hf_generate(model: str, dtype: str, device: str, max_batch_size: int, options: dict[str, Any]) -> InferenceEngine:
    """The transformers engine: runs anywhere torch does (the CPU default)."""
    from infinirl.engines.hf_generate import HFGenerateEngine
    from infinirl.models.hf_causal_lm import load_causal_lm

    hf_model, tokenizer = load_causal_lm(model, dtype=dtype, device=device)
    return HFGenerateEngine(hf_model, tokenizer, max_batch_size=max_batch_size, **options)


@ROLLOUT_ENGINES.register("vllm")
def _vllm(model: str, dtype: str, device: str, max_batch_size: int, options: dict[str, Any]) -> InferenceEngine:
    """vLLM (optional extra, its own venv: scripts/setup_vllm_venv.sh). ``options`` are
    ``VLLMEngine`` keyword arguments, e.g. ``kv_cache_bytes``, ``max_model_len``, ``sleep_level``."""
    from infinirl.engines.vllm_engine import VLLMEngine

    return VLLMEngine(model, dtype=dtype, device=device, max_batch_size=max_batch_size, **options)


#: The engine class behind each built-in factory and the arguments the factory fills itself: what
#: ``rollout.engine_options`` may name is read off its signature (an engine from a plugin is not checked).
_OPTIONS_OF: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "hf": ("infinirl.engines.hf_generate", "HFGenerateEngine", ("model", "tokenizer", "max_batch_size")),
    "vllm": ("infinirl.engines.vllm_engine", "VLLMEngine", ("model", "dtype", "device", "max_batch_size")),
}


def check_engine_options(name: str, options: dict[str, Any], key: str) -> None:
    """Refuse an option engine ``name`` does not take, naming ``key.<option>``, before any worker starts."""
    from infinirl.config import ConfigError

    if name not in _OPTIONS_OF or not options:
        return
    import importlib

    from infinirl.utils.signatures import keyword_names

    module, cls, filled = _OPTIONS_OF[name]
    taken, open_ended = keyword_names(getattr(importlib.import_module(module), cls))
    for option in options:
        if option in filled:
            raise ConfigError(f"{key}.{option}: the runner sets it for the {name} engine; remove it from {key}")
        if not open_ended and option not in taken:
            allowed = ", ".join(sorted(taken - set(filled))) or "no options"
            raise ConfigError(f"{key}.{option}: the {name} engine takes {allowed}")


def build_rollout_engine(name: str, model: str, dtype: str, device: str, max_batch_size: int,
                         options: dict[str, Any] | None = None) -> InferenceEngine:
    if device == "cpu":
        from infinirl.engines.cpu_dtype import resolve_cpu_dtype

        dtype = resolve_cpu_dtype(dtype)  # bf16 becomes float32 on CPUs without native bf16
    return ROLLOUT_ENGINES.get(name)(model, dtype, device, max_batch_size, dict(options or {}))
