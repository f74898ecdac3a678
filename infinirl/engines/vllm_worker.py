"""Functions run on vLLM's worker, each as ``llm.collective_rpc(fn, args=...)``, i.e.
``fn(worker, *args)``, where ``worker`` is vLLM's worker wrapper (attributes fall through to the
CPU/GPU worker)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch

__all__ = ["GREEDY_EPS", "free_kv_cache", "install_tempered_logprobs", "kv_cache_bytes", "reload_arguments",
           "reload_weights", "restore_kv_cache"]

GREEDY_EPS = 1e-5  # vLLM treats temperature below this as greedy


def install_tempered_logprobs(worker) -> str:
    """Make the sampler's raw log-probs ``log softmax(logits / T)`` with each row's temperature
    (``T = 1`` on greedy rows), computed before any top-k/top-p masking."""
    from vllm.v1.sample.sampler import Sampler

    sampler = worker.model_runner.sampler
    if type(sampler) is not Sampler or sampler.logprobs_mode != "raw_logprobs":
        raise RuntimeError(
            f"VLLMEngine: expected vLLM's V1 Sampler in raw_logprobs mode, found "
            f"{type(sampler).__name__} ({getattr(sampler, 'logprobs_mode', '?')}); this vLLM "
            "version is not supported (scripts/setup_vllm_venv.sh pins a tested one)"
        )
    if getattr(sampler, "_infinirl_tempered", False):
        return "already installed"
    base_forward = sampler.forward
    state: dict[str, Any] = {"metadata": None}

    def forward(logits, sampling_metadata, *args, **kwargs):
        state["metadata"] = sampling_metadata
        try:
            return base_forward(logits, sampling_metadata, *args, **kwargs)
        finally:
            state["metadata"] = None

    def compute_logprobs(logits: torch.Tensor) -> torch.Tensor:
        metadata = state["metadata"]
        if metadata is not None and not metadata.all_greedy and metadata.temperature is not None:
            temperature = metadata.temperature
            if len(temperature) != len(logits):
                raise RuntimeError(
                    f"VLLMEngine: {len(logits)} logit rows for {len(temperature)} requests; "
                    "tempered log-probs need one row per request (speculative decoding is not "
                    "supported)"
                )
            temperature = torch.where(
                temperature < GREEDY_EPS, torch.ones_like(temperature), temperature
            )
            logits = logits.to(torch.float32) / temperature.unsqueeze(1)
        return logits.log_softmax(dim=-1, dtype=torch.float32)

    sampler.forward = forward  # nn.Module.__call__ dispatches to the instance attribute
    sampler.compute_logprobs = compute_logprobs
    sampler._infinirl_tempered = True
    return "installed"


def reload_arguments(worker) -> list[str] | None:
    """The keyword arguments the worker's ``reload_weights`` takes (None: it has none)."""
    import inspect

    from infinirl.engines.vllm_process import RELOAD_ARGUMENTS

    method = getattr(worker, "reload_weights", None)
    if method is None:
        return None
    parameters = inspect.signature(method).parameters.values()
    names = [p.name for p in parameters]
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        names += RELOAD_ARGUMENTS  # passed on unchecked: the call itself will tell
    return names


def reload_weights(worker, named_tensors: Iterable[tuple[str, torch.Tensor]]) -> None:
    """vLLM's in-place reload, then re-run post-load processing of (tied) LM heads."""
    from vllm.model_executor.layers.vocab_parallel_embedding import ParallelLMHead

    worker.reload_weights(weights_iterator=named_tensors, is_checkpoint_format=True)
    model = worker.model_runner.get_model()
    for module in model.modules():
        if isinstance(module, ParallelLMHead) and module.weight.numel():
            module.quant_method.process_weights_after_loading(module)


def free_kv_cache(worker) -> int:
    """Release the KV cache's memory but keep its storages, so every view vLLM holds of them (per
    layer, per attention backend) stays valid; returns the bytes released."""
    storages = {}
    for tensor in worker.model_runner.kv_caches:  # layers may share one buffer
        storage = tensor.untyped_storage()
        if storage.nbytes():
            storages.setdefault(storage.data_ptr(), storage)
    freed = [(storage, storage.nbytes()) for storage in storages.values()]
    for storage, _ in freed:
        storage.resize_(0)
    worker._infinirl_freed_kv = freed
    return sum(size for _, size in freed)


def restore_kv_cache(worker) -> int:
    """Reallocate what :func:`free_kv_cache` released, zeroed: a fresh cache, contents forgotten."""
    freed = getattr(worker, "_infinirl_freed_kv", None) or []
    for storage, size in freed:
        storage.resize_(size)
        torch.empty(0, dtype=torch.uint8).set_(storage).zero_()
    worker._infinirl_freed_kv = None
    return sum(size for _, size in freed)


def kv_cache_bytes(worker) -> int:
    """Bytes currently allocated to the KV cache (0 while freed)."""
    seen = {}
    for tensor in worker.model_runner.kv_caches:
        storage = tensor.untyped_storage()
        seen[storage.data_ptr()] = storage.nbytes()
    return sum(seen.values())
