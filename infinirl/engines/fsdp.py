"""Training engine on FSDP2 (``torch.distributed.fsdp.fully_shard``) over any HF causal LM.

Why FSDP2: parameters are per-parameter ``DTensor`` shards, so frozen and trainable weights (LoRA)
live in the same group, state dicts need no flat-parameter translation, and the same code runs on
one CPU process (gloo, world size 1) and on many GPUs (NCCL).

Data parallelism and the loss contract
--------------------------------------
Every rank gets its own share of a mini-batch. The caller's ``loss_fn`` is normalised by a *global*
denominator (e.g. the number of response tokens in the whole mini-batch over all ranks), so the
gradient of the mini-batch loss is the **sum** of the per-micro-batch, per-rank gradients. FSDP2
averages over ranks by default; we set ``gradient_divide_factor=1`` and force plain ``SUM``
collectives on *every* FSDP module (``set_force_sum_reduction_for_comms``; neither setter recurses
into sub-modules, and setting only the root silently leaves the layers averaging), so the
reduce-scatter sums and nothing divides. (``SUM`` rather than NCCL's ``PREMUL_SUM(1.0)`` because gloo has no
``PREMUL_SUM``; the result is the same.) Micro-batch gradients simply accumulate, undivided.

All collectives must match across ranks, so ranks with fewer micro-batches than the busiest rank
run zero-loss filler passes (see :meth:`FSDPTrainEngine._micro_batch_plan`).

Policies, critics and references
--------------------------------
One engine serves the three model roles of PPO. ``output="logprobs"`` (a causal LM: the actor, or
with ``trainable=False`` a frozen reference) gives per-token log-probs; ``output="values"`` (a
token-classification model with one label: backbone + scalar value head, the critic) gives
per-token values. Both come in the aligned layout of :mod:`infinirl.data.batch`, and the loss
contract, sharding, micro-batching and checkpoints are the same code for all three.

Process groups
--------------
:func:`init_distributed` joins the default group from ``RANK/WORLD_SIZE/MASTER_ADDR/MASTER_PORT``
(gloo for CPU engines; ``cuda:nccl,cpu:gloo`` for GPU engines), or, without those variables,
makes a one-rank group in-process. The engine never destroys a group: the worker that owns the
process does.
"""

from __future__ import annotations

import os
import shutil
import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import torch
import torch.distributed as dist
import torch.distributed.checkpoint as dcp
from tensordict import TensorDict
from torch import nn
from torch.distributed.checkpoint.state_dict import (
    get_model_state_dict,
    get_optimizer_state_dict,
    set_model_state_dict,
    set_optimizer_state_dict,
)
from torch.distributed.device_mesh import init_device_mesh
from torch.distributed.fsdp import FSDPModule, MixedPrecisionPolicy, fully_shard
from torch.distributed.tensor import DTensor

from infinirl.data.batch import ATTENTION_MASK, INPUT_IDS, POSITION_IDS, RESPONSE_MASK
from infinirl.engines.cpu_dtype import resolve_cpu_dtype
from infinirl.engines.logprobs import aligned_logprobs, aligned_values
from infinirl.engines.shared_prefix import pack_by_prompt, packed_logprobs, supports_packed_masks
from infinirl.engines.train_base import LoraSettings, LossFn, LrSchedule, TrainEngineConfig, TrainOutput
from infinirl.utils import capture_rng_state, replace_directory, restore_rng_state, seed_everything

ModelOrFactory = nn.Module | Callable[[], nn.Module]

_DCP_DIR = "model_optim"  # DCP shards of model + optimizer (resharding-capable)
_ENGINE_STATE = "engine_rank{rank}.pt"  # per-rank: scheduler, step, RNG (RNG differs per rank)
_PEFT_PREFIX = "base_model.model."
_ADAPTER = "default"


# ----------------------------------------------------------------------------- process group


def init_distributed(device_type: str = "cpu") -> bool:
    """Make sure the default process group exists; return True if this call created it.

    With ``MASTER_ADDR`` set (a launched worker) it joins via ``env://`` using ``RANK`` and
    ``WORLD_SIZE``; otherwise it creates a one-rank group on an in-memory store, so a plain script
    or test needs no setup. ``device_type`` picks the backend: gloo for CPU engines, and
    ``cuda:nccl,cpu:gloo`` for CUDA engines (NCCL for tensors on GPU, gloo for CPU-side objects).
    An existing group is checked against ``device_type``, since the wrong backend would only fail
    later, deep inside FSDP.
    """
    if dist.is_initialized():
        _check_backend(device_type)
        return False
    backend = "cuda:nccl,cpu:gloo" if device_type == "cuda" else "gloo"
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if "MASTER_ADDR" in os.environ:
        dist.init_process_group(
            backend, rank=int(os.environ.get("RANK", "0")), world_size=world_size
        )
    elif world_size == 1:
        dist.init_process_group(backend, store=dist.HashStore(), rank=0, world_size=1)
    else:
        raise RuntimeError(
            f"init_distributed: WORLD_SIZE={world_size} but MASTER_ADDR/MASTER_PORT are not set; "
            "the launcher must export them so ranks can meet."
        )
    return True


def _check_backend(device_type: str) -> None:
    backend = str(dist.get_backend())
    needed = "nccl" if device_type == "cuda" else "gloo"
    if needed not in backend:
        raise RuntimeError(
            f"the default process group uses backend {backend!r}, but a {device_type} engine needs "
            f"{needed} (init with 'cuda:nccl,cpu:gloo' on GPU, 'gloo' on CPU, or let "
            "init_distributed() create the group)"
        )


def _device_type(choice: str) -> str:
    if choice == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("TrainEngineConfig.device='cuda' but CUDA is not available")
    if choice == "cpu" or (choice == "auto" and not torch.cuda.is_available()):
        return "cpu"
    return "cuda"


def _select_device(device_type: str) -> torch.device:
    if device_type == "cpu":
        return torch.device("cpu")
    # A Ray worker usually sees exactly one GPU; torchrun-style launches see all and use LOCAL_RANK.
    local_rank = int(os.environ.get("LOCAL_RANK", dist.get_rank() % torch.cuda.device_count()))
    torch.cuda.set_device(local_rank)
    return torch.device("cuda", local_rank)


def _compute_dtype(choice: str, device: torch.device) -> torch.dtype:
    if choice == "float32":
        return torch.float32
    if choice == "bfloat16":
        if device.type == "cpu":
            return getattr(torch, resolve_cpu_dtype("bfloat16"))  # float32 on CPUs without native bf16
        return torch.bfloat16
    if device.type == "cuda" and torch.cuda.is_bf16_supported():
        return torch.bfloat16
    return torch.float32


# ----------------------------------------------------------------------------- model preparation


def _enable_activation_checkpointing(model: nn.Module) -> None:
    if not getattr(model, "supports_gradient_checkpointing", False):
        raise ValueError(
            f"activation_checkpointing=True but {type(model).__name__} does not support HF "
            "gradient checkpointing (supports_gradient_checkpointing is False)"
        )
    # Non-reentrant: works with frozen inputs (LoRA) and with FSDP2's hooks; keeps parameter names.
    kwargs = {"use_reentrant": False}
    if hasattr(model, "activation_checkpointing_enable"):  # transformers >= 5 name
        model.activation_checkpointing_enable(activation_checkpointing_kwargs=kwargs)
    else:
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs=kwargs)


def _apply_lora(
    model: nn.Module, settings: LoraSettings, fully_trained: list[str] | None = None
) -> nn.Module:
    """Wrap ``model`` with LoRA adapters; modules named in ``fully_trained`` (a critic's freshly
    initialised value head) get no adapter and train in full (peft's ``modules_to_save``)."""
    from peft import LoraConfig, get_peft_model
    from peft.tuners.lora import Linear as LoraLinear
    from peft.tuners.lora import LoraLayer

    layers = None
    if settings.top_layers:
        total = int(model.config.num_hidden_layers)
        if not 0 < settings.top_layers <= total:
            raise ValueError(f"lora.top_layers={settings.top_layers}: the model has {total} decoder layers; "
                             f"use 1..{total}, or 0 for all")
        layers = list(range(total - settings.top_layers, total))
    targets = settings.target_modules
    if layers is not None and targets == "all-linear":  # peft wants explicit names with a layer filter
        skip = {"lm_head", *(fully_trained or [])}
        targets = sorted({name.rsplit(".", 1)[-1] for name, module in model.named_modules()
                          if isinstance(module, nn.Linear) and name.rsplit(".", 1)[-1] not in skip})
    config = LoraConfig(
        r=settings.r,
        lora_alpha=settings.alpha,
        target_modules=targets,
        lora_dropout=settings.dropout,
        bias="none",
        modules_to_save=fully_trained,
        layers_to_transform=layers,
    )
    peft_model = get_peft_model(model, config)
    for name, module in peft_model.named_modules():
        if isinstance(module, LoraLayer) and not isinstance(module, LoraLinear):
            raise ValueError(
                f"LoRA target {name!r} is a {type(module).__name__}; only nn.Linear targets are "
                "supported (their merge for weight sync is implemented). Narrow target_modules."
            )
    return peft_model


def _value_head_name(model: nn.Module) -> str:
    """The attribute holding a token-classification model's output layer (``score`` in
    transformers' generic heads, ``classifier`` in some older families)."""
    for name in ("score", "classifier"):
        if isinstance(getattr(model, name, None), nn.Linear):
            return name
    raise ValueError(
        f"{type(model).__name__} has no 'score'/'classifier' linear head; a critic needs a "
        "token-classification model with one output (backbone + scalar value head)"
    )


def _decoder_layers(model: nn.Module) -> list[nn.Module]:
    """Modules to shard as separate FSDP groups: HF's ``_no_split_modules`` (the decoder layers).

    One group per layer lets FSDP all-gather one layer at a time (peak memory ~ one layer) and
    overlap communication with the previous layer's compute.
    """
    class_names: set[str] = set()
    for module in model.modules():
        class_names.update(getattr(module, "_no_split_modules", None) or [])
    return [m for m in model.modules() if type(m).__name__ in class_names]


def _shard(model: nn.Module, mesh, compute_dtype: torch.dtype) -> nn.Module:
    mp_policy = MixedPrecisionPolicy(param_dtype=compute_dtype, reduce_dtype=torch.float32)
    for layer in _decoder_layers(model):
        fully_shard(layer, mesh=mesh, mp_policy=mp_policy)
    fully_shard(model, mesh=mesh, mp_policy=mp_policy)
    for module in model.modules():
        if isinstance(module, FSDPModule):
            # SUM across ranks instead of FSDP's default mean: see the module docstring.
            module.set_gradient_divide_factor(1.0)
            module.set_force_sum_reduction_for_comms(True)
    return model


def _lora_merge_plan(model: nn.Module) -> dict[str, tuple[float, bool]]:
    """``{module FQN: (scaling, fan_in_fan_out)}`` for every LoRA-wrapped linear layer."""
    from peft.tuners.lora import LoraLayer

    return {
        name: (float(module.scaling[_ADAPTER]), bool(getattr(module, "fan_in_fan_out", False)))
        for name, module in model.named_modules()
        if isinstance(module, LoraLayer)
    }


def _full_tensor(tensor: torch.Tensor) -> torch.Tensor:
    """Unshard a DTensor (a collective: every rank must call it in the same order)."""
    return tensor.full_tensor() if isinstance(tensor, DTensor) else tensor


def _as_tensordict(batch: TensorDict | Mapping[str, torch.Tensor]) -> TensorDict:
    if isinstance(batch, TensorDict):
        return batch
    if INPUT_IDS not in batch:
        raise KeyError(f"batch needs {INPUT_IDS!r}; got keys {sorted(batch)}")
    return TensorDict(dict(batch), batch_size=[batch[INPUT_IDS].shape[0]])


def _used_width(attention_mask: torch.Tensor) -> int:
    """Columns up to the last attended token of any row: trailing all-pad columns are skipped."""
    positions = torch.arange(1, attention_mask.shape[1] + 1, device=attention_mask.device)
    return max(1, int((positions * (attention_mask != 0)).max()))


def _pad_columns(scores: torch.Tensor, width: int, left: int = 0) -> torch.Tensor:
    """Zero columns: ``left`` before the scores and as many after as make ``width``."""
    if scores.shape[1] == width and not left:
        return scores
    return torch.nn.functional.pad(scores, (left, width - left - scores.shape[1]))


def _first_scored_column(micro_batch: TensorDict, width: int) -> int:
    """The first column whose logits any row's response needs: one before the earliest response
    token (``response_mask``), or 0 when the batch does not say which tokens are responses."""
    mask = micro_batch.get(RESPONSE_MASK, None)
    if mask is None or width < 2:
        return 0
    mask = mask[:, :width].to(torch.bool)
    if not bool(mask.any()):
        return 0
    first = int(mask.any(dim=0).to(torch.int8).argmax())
    return max(0, first - 1)


# ----------------------------------------------------------------------------- the engine


class FSDPTrainEngine:
    """Train a causal LM with FSDP2 across the ranks of the default process group.

    Args:
        model: an HF causal LM or a zero-argument factory building one. A factory runs on every
            rank after ``torch.manual_seed(cfg.seed)``, so random initialisations agree across
            ranks; it must be deterministic (pretrained weights are). Weights become float32
            master weights; ``cfg.param_dtype`` only sets the compute dtype.
        cfg: optimiser, schedule, batching, precision, LoRA (see :class:`TrainEngineConfig`).
        output: what the model's per-token output means. ``"logprobs"``: an HF causal LM whose
            logits become aligned token log-probs (policy, reference). ``"values"``: an HF
            token-classification model with one label whose outputs become aligned values
            (critic): ``values[:, t]`` is read from the hidden state *before* token ``t``, the
            state in which token ``t`` is chosen, as GAE expects.
        trainable: ``False`` freezes every weight and builds no optimizer (a reference policy):
            only the forward methods work, and no gradient memory is ever allocated.
    """

    def __init__(
        self,
        model: ModelOrFactory,
        cfg: TrainEngineConfig,
        output: TrainOutput = "logprobs",
        trainable: bool = True,
    ):
        if output not in ("logprobs", "values"):
            raise ValueError(f"FSDPTrainEngine: output must be 'logprobs' or 'values', got {output!r}")
        if not trainable and cfg.lora is not None:
            raise ValueError("FSDPTrainEngine: a frozen engine (trainable=False) takes no LoRA adapters")
        self.cfg = cfg
        self.output = output
        self.trainable = trainable
        device_type = _device_type(cfg.device)
        init_distributed(device_type)
        self.rank = dist.get_rank()
        self.world_size = dist.get_world_size()
        self.device = _select_device(device_type)
        self.compute_dtype = _compute_dtype(cfg.param_dtype, self.device)

        seed_everything(cfg.seed)  # identical init on every rank
        if not isinstance(model, nn.Module):
            model = model()
        model = model.to(device=self.device, dtype=torch.float32)
        self._packable = supports_packed_masks(getattr(model, "config", None))
        if cfg.activation_checkpointing:
            _enable_activation_checkpointing(model)
        self._lora_plan: dict[str, tuple[float, bool]] = {}
        if cfg.lora is not None:
            heads = [_value_head_name(model)] if output == "values" else None
            model = _apply_lora(model, cfg.lora, fully_trained=heads)
            self._lora_plan = _lora_merge_plan(model)
        if not trainable:
            model.requires_grad_(False)
        self.mesh = init_device_mesh(self.device.type, (self.world_size,))
        self.model = _shard(model, self.mesh, self.compute_dtype)

        self.optimizer: torch.optim.Optimizer | None = None
        self.scheduler: torch.optim.lr_scheduler.LambdaLR | None = None
        if trainable:
            params = [p for p in self.model.parameters() if p.requires_grad]
            if not params:
                raise ValueError("FSDPTrainEngine: the model has no trainable parameters")
            self.optimizer = torch.optim.AdamW(
                params, lr=cfg.lr, betas=cfg.betas, eps=cfg.eps, weight_decay=cfg.weight_decay
            )
            self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, LrSchedule(cfg))
        self.global_step = 0
        self._offloaded = False
        seed_everything(cfg.seed + self.rank)  # runtime randomness (dropout) differs per rank

    @classmethod
    def from_pretrained(
        cls,
        name_or_path: str,
        cfg: TrainEngineConfig,
        output: TrainOutput = "logprobs",
        trainable: bool = True,
        **hf_kwargs,
    ) -> FSDPTrainEngine:
        """Build from an HF checkpoint directory (loaded in float32 on every rank).

        With ``output="values"`` the checkpoint (usually the policy's own causal LM) becomes a
        critic: its backbone under a new scalar value head (``AutoModelForTokenClassification``
        with one label, as verl does), without dropout, and with the head initialised to zero so
        every value starts at 0 (GAE then starts as the plain reward-to-go, not from noise).
        """
        from transformers import AutoConfig, AutoModelForCausalLM, AutoModelForTokenClassification

        def factory() -> nn.Module:
            if output == "logprobs":
                return AutoModelForCausalLM.from_pretrained(
                    name_or_path, dtype=torch.float32, **hf_kwargs
                )
            config = AutoConfig.from_pretrained(name_or_path, num_labels=1)
            config.classifier_dropout = 0.0  # noise in the regression target's fit: none
            try:
                model = AutoModelForTokenClassification.from_pretrained(
                    name_or_path, config=config, dtype=torch.float32, **hf_kwargs
                )
            except ValueError as exc:  # transformers: "Unrecognized configuration class ..."
                raise ValueError(
                    f"cannot build a critic from {name_or_path}: transformers has no "
                    f"token-classification head for this architecture ({exc})"
                ) from None
            head = getattr(model, _value_head_name(model))
            with torch.no_grad():
                head.weight.zero_()
                if head.bias is not None:
                    head.bias.zero_()
            return model

        return cls(factory, cfg, output=output, trainable=trainable)

    # ------------------------------------------------------------------ forward

    @torch.no_grad()
    def compute_logprobs(
        self,
        batch: TensorDict | Mapping[str, torch.Tensor],
        with_entropy: bool = False,
        adapter: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Aligned ``[B, L]`` float32 log-probs (and entropies) of this rank's batch, no grad.

        ``adapter=False`` scores with the LoRA adapters switched off: the frozen base model, which
        is the initial policy, i.e. the reference of a LoRA actor at no extra memory.
        Collective: every rank must call it (with its own, possibly differently sized, batch).
        """
        self._require_output("logprobs", "compute_logprobs")
        if adapter:
            return self._forward_only(batch, with_entropy)
        if not self._lora_plan:
            raise ValueError("compute_logprobs(adapter=False) needs a LoRA engine (cfg.lora is None)")
        with self.model.disable_adapter():
            return self._forward_only(batch, with_entropy)

    @torch.no_grad()
    def compute_values(self, batch: TensorDict | Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Aligned ``[B, L]`` float32 values of this rank's batch (0 at position 0 and on padding),
        no grad. Collective, like :meth:`compute_logprobs`."""
        self._require_output("values", "compute_values")
        values, _ = self._forward_only(batch, with_entropy=False)
        return values

    def _forward_only(
        self, batch: TensorDict | Mapping[str, torch.Tensor], with_entropy: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        self._require_on_device("compute_logprobs" if self.output == "logprobs" else "compute_values")
        batch = _as_tensordict(batch).to(self.device)
        self.model.eval()
        micro_batches, passes = self._micro_batch_plan(batch)
        logprobs, entropies = [], []
        for index in range(passes):
            if index < len(micro_batches):
                lp, ent = self._forward(micro_batches[index], with_entropy)
                logprobs.append(lp)
                entropies.append(ent)
            else:
                self._forward(self._filler_batch(), with_entropy=False)
        # FSDP2 reshards the root group (embeddings, LM head: the largest matrices) only after a
        # backward, so after no-grad forwards it would keep them unsharded: free that memory now.
        self.model.reshard()
        width = batch[INPUT_IDS].shape[1]
        if not logprobs:
            empty = torch.zeros(0, width, device=self.device)
            return empty, (empty.clone() if with_entropy else None)
        return torch.cat(logprobs), (torch.cat(entropies) if with_entropy else None)

    def _forward(
        self, micro_batch: TensorDict, with_entropy: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        input_ids = micro_batch[INPUT_IDS]
        full_width = input_ids.shape[1]
        attention_mask = micro_batch.get(ATTENTION_MASK, None)
        if attention_mask is None:
            attention_mask = torch.ones_like(input_ids)
        position_ids = micro_batch.get(POSITION_IDS, None)
        width = _used_width(attention_mask)
        input_ids, attention_mask = input_ids[:, :width], attention_mask[:, :width]
        if position_ids is not None:
            position_ids = position_ids[:, :width]
        if self._shares_prompt_prefix:
            response_mask = micro_batch.get(RESPONSE_MASK, None)
            packed = pack_by_prompt(input_ids, attention_mask, position_ids,
                                    None if response_mask is None else response_mask[:, :width],
                                    mask_dtype=self.compute_dtype, max_packed_tokens=self.cfg.max_packed_tokens)
            logprobs, entropy = packed_logprobs(self.model, packed, (input_ids.shape[0], full_width),
                                                self.cfg.temperature, self.cfg.logprob_chunk_tokens, with_entropy)
            return logprobs, entropy
        # Log-probs are only ever read at response tokens: the LM head (and the full-vocabulary
        # softmax behind it) runs from the column before the earliest response token on, not over
        # the prompts. Exact: the kept positions' logits are the same numbers either way.
        scored_from = self.output != "values" and not self.cfg.score_prompts
        start = _first_scored_column(micro_batch, width) if scored_from else 0
        extra = {"logits_to_keep": width - start} if start > 0 else {}
        output = self.model(
            input_ids=input_ids,
            attention_mask=attention_mask,
            position_ids=position_ids,
            use_cache=False,
            **extra,
        )
        if self.output == "values":
            values = aligned_values(output.logits.squeeze(-1), attention_mask)
            return _pad_columns(values, full_width), None
        logits = output.logits
        if logits.shape[1] == width and start > 0:  # a model that ignores logits_to_keep
            logits = logits[:, start:]
        logprobs, entropy = aligned_logprobs(
            logits,
            input_ids[:, start:],
            attention_mask[:, start:],
            temperature=self.cfg.temperature,
            chunk_tokens=self.cfg.logprob_chunk_tokens,
            with_entropy=with_entropy,
        )
        logprobs = _pad_columns(logprobs, full_width, left=start)
        return logprobs, (_pad_columns(entropy, full_width, left=start) if entropy is not None else None)

    @property
    def _shares_prompt_prefix(self) -> bool:
        """Config only (never the data): every rank must make the same number of model calls."""
        cfg = self.cfg
        return (self.output == "logprobs" and cfg.share_prompt_prefix and not cfg.score_prompts
                and not cfg.activation_checkpointing and self._packable)

    def _micro_batch_plan(self, batch: TensorDict) -> tuple[list[TensorDict], int]:
        """This rank's micro-batches, and how many passes every rank must make (the global max).

        FSDP all-gathers parameters in every forward and reduce-scatters gradients in every
        backward; a rank that stopped early would leave the others waiting forever.
        """
        size = batch.batch_size[0]
        micro_batches = list(batch.split(self.cfg.micro_batch_size)) if size else []
        count = torch.tensor([len(micro_batches)], device=self.device)
        dist.all_reduce(count, op=dist.ReduceOp.MAX)
        return micro_batches, int(count.item())

    def _filler_batch(self) -> TensorDict:
        one = torch.ones(1, 1, dtype=torch.long, device=self.device)
        return TensorDict(
            {INPUT_IDS: one * 0, ATTENTION_MASK: one, POSITION_IDS: one * 0},
            batch_size=[1],
            device=self.device,
        )

    # ------------------------------------------------------------------ training

    def train_step(
        self,
        batch: TensorDict | Mapping[str, torch.Tensor],
        loss_fn: LossFn,
        with_entropy: bool = False,
    ) -> dict[str, float]:
        """One optimizer step on this rank's share of a mini-batch.

        ``loss_fn(micro_batch, logprobs, entropy)`` runs per micro-batch; gradients are summed over
        micro-batches and ranks (the loss carries the global normaliser). Collective. For a value
        engine the second argument holds the values (and the entropy is ``None``).

        Returns the loss function's metrics averaged over all micro-batches of all ranks, plus
        ``train/loss`` (the mini-batch loss: summed, like the gradients), ``train/grad_norm``
        (global, before clipping), ``train/lr`` (used by this step), ``train/skipped_step``
        (1 when the gradient was not finite and the update was skipped) and ``time/train_step``.
        """
        start = time.perf_counter()
        self._require_trainable("train_step")
        self._require_on_device("train_step")
        batch = _as_tensordict(batch).to(self.device)
        self.model.train()
        micro_batches, passes = self._micro_batch_plan(batch)
        if passes == 0:
            raise ValueError("train_step: the mini-batch is empty on every rank")
        self.optimizer.zero_grad(set_to_none=True)
        try:
            loss_sum, metric_sums = self._accumulate_gradients(
                micro_batches, passes, loss_fn, with_entropy
            )
        except BaseException:
            # FSDP's per-iteration state is undefined after a failed forward/backward; reset it and
            # drop partial gradients so the engine stays usable (the step is simply not taken).
            if hasattr(self.model, "reset_iter_state"):  # torch >= 2.13
                self.model.reset_iter_state()
            self.optimizer.zero_grad(set_to_none=True)
            raise

        grad_norm = self._clip_grad_norm()
        finite = bool(torch.isfinite(grad_norm))
        lr = self.scheduler.get_last_lr()[0]
        if finite:
            self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        with warnings.catch_warnings():
            # A skipped update still advances the schedule (it counts train steps); torch warns
            # about stepping the scheduler without the optimizer, which is intended here.
            warnings.filterwarnings(
                "ignore", message="Detected call of `lr_scheduler.step", category=UserWarning
            )
            self.scheduler.step()
        self.global_step += 1

        dist.all_reduce(loss_sum)
        out = self._average_metrics(metric_sums, len(micro_batches))
        out.update(
            {
                "train/loss": float(loss_sum),
                "train/grad_norm": float(grad_norm),
                "train/lr": lr,
                "train/skipped_step": 0.0 if finite else 1.0,
                "time/train_step": time.perf_counter() - start,
            }
        )
        return out

    def _accumulate_gradients(
        self, micro_batches: list[TensorDict], passes: int, loss_fn: LossFn, with_entropy: bool
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Forward/backward every micro-batch (plus fillers); FSDP sums their gradients."""
        loss_sum = torch.zeros((), device=self.device)
        metric_sums: dict[str, torch.Tensor | float] = {}
        for index in range(passes):
            if index < len(micro_batches):
                micro_batch = micro_batches[index]
                logprobs, entropy = self._forward(micro_batch, with_entropy)
                loss, metrics = loss_fn(micro_batch, logprobs, entropy)
                _check_loss(loss)
                for (
                    key,
                    value,
                ) in metrics.items():  # tensors stay on device: no sync per micro-batch
                    value = (
                        value.detach().float() if isinstance(value, torch.Tensor) else float(value)
                    )
                    metric_sums[key] = metric_sums.get(key, 0.0) + value
                loss_sum += loss.detach().float()
            else:  # filler: joins the collectives, contributes zero gradient
                logprobs, _ = self._forward(self._filler_batch(), with_entropy=False)
                loss = logprobs.sum() * 0.0
            loss.backward()
        return loss_sum, {key: float(value) for key, value in metric_sums.items()}

    def _clip_grad_norm(self) -> torch.Tensor:
        """Global L2 norm of all gradients (sharded ones included); clip to ``cfg.grad_clip``."""
        params = [p for p in self.model.parameters() if p.grad is not None]
        if not params:
            return torch.zeros((), device=self.device)
        total = torch.nn.utils.get_total_norm([p.grad for p in params], norm_type=2.0)
        total = _full_tensor(total)  # partial per-shard norms -> the global norm
        if self.cfg.grad_clip and torch.isfinite(total):
            torch.nn.utils.clip_grads_with_norm_(params, self.cfg.grad_clip, total)
        return total

    def _average_metrics(self, sums: dict[str, float], count: int) -> dict[str, float]:
        """Mean over every real micro-batch of every rank (each micro-batch weighs the same)."""
        gathered: list = [None] * self.world_size
        dist.all_gather_object(gathered, (sums, count))
        totals: dict[str, float] = {}
        counts: dict[str, int] = {}
        for rank_sums, rank_count in gathered:
            for key, value in rank_sums.items():
                totals[key] = totals.get(key, 0.0) + value
                counts[key] = counts.get(key, 0) + rank_count
        return {key: totals[key] / counts[key] for key in totals}

    # ------------------------------------------------------------------ weight export

    def state_dict_for_sync(
        self, dtype: torch.dtype | None = None
    ) -> Iterator[tuple[str, torch.Tensor]]:
        """Yield ``(name, full tensor)`` per parameter, named like the HF model's ``state_dict()``.

        Gathered on **every** rank (each ``DTensor.full_tensor()`` is an all-gather), one tensor
        at a time so peak memory is one full parameter, which suits bucketed sync. Every rank must
        consume the iterator to the end. LoRA adapters are merged into their base weights and
        their own entries are not yielded. Tensors stay on the engine's device; ``dtype`` casts.
        """
        self._require_on_device("state_dict_for_sync")
        sharded = self.model.state_dict()
        for name, tensor in sharded.items():
            if self._lora_plan and (".lora_A." in name or ".lora_B." in name):
                continue
            full = _full_tensor(tensor.detach())
            module_name, _, leaf = name.rpartition(".base_layer.")
            if leaf == "weight" and module_name in self._lora_plan:
                full = full + self._lora_delta(sharded, module_name)
            yield _hf_name(name), (full.to(dtype) if dtype is not None else full)

    def _lora_delta(self, sharded: Mapping[str, torch.Tensor], module_name: str) -> torch.Tensor:
        scaling, fan_in_fan_out = self._lora_plan[module_name]
        lora_a = _full_tensor(sharded[f"{module_name}.lora_A.{_ADAPTER}.weight"].detach())
        lora_b = _full_tensor(sharded[f"{module_name}.lora_B.{_ADAPTER}.weight"].detach())
        delta = (lora_b @ lora_a) * scaling
        return delta.T if fan_in_fan_out else delta

    # ------------------------------------------------------------------ checkpoints

    def save_checkpoint(self, path: str | os.PathLike) -> None:
        """Write model + optimizer (DCP shards), scheduler, step and per-rank RNG to ``path``.

        Atomic: everything goes to ``<path>.tmp`` and rank 0 renames it into place only after all
        ranks finished, so ``path`` is either the old checkpoint or the complete new one. On an
        error the temporary directory is removed. With several nodes ``path`` must be on a shared
        filesystem (every rank writes its own shards). Collective.
        """
        self._require_trainable("save_checkpoint")
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        with self._temporarily_on_device():
            if self.rank == 0:
                shutil.rmtree(tmp, ignore_errors=True)
                tmp.mkdir(parents=True)
            self._barrier()
            try:
                has_optimizer_state = bool(self.optimizer.state)
                state = {"model": get_model_state_dict(self.model)}
                if has_optimizer_state:  # reading an empty optimizer's state would initialise it
                    state["optimizer"] = get_optimizer_state_dict(self.model, self.optimizer)
                dcp.save(state, checkpoint_id=str(tmp / _DCP_DIR))
                torch.save(self._engine_state(has_optimizer_state), tmp / _ENGINE_STATE.format(rank=self.rank))
                self._barrier()
                if self.rank == 0:
                    replace_directory(tmp, path)
                self._barrier()
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Restore a :meth:`save_checkpoint` directory. Collective.

        Model and optimizer reshard to any world size (DCP); each rank restores its own RNG, or
        rank 0's when the checkpoint came from fewer ranks. The lr schedule's position *and* its
        parameters (warmup, horizon) come from the checkpoint, as ``LambdaLR`` stores them.
        """
        self._require_trainable("load_checkpoint")
        path = Path(path)
        if not (path / _DCP_DIR).is_dir():
            raise FileNotFoundError(
                f"load_checkpoint: {path} is not an engine checkpoint (no {_DCP_DIR}/)"
            )
        engine_file = path / _ENGINE_STATE.format(rank=self.rank)
        if not engine_file.exists():  # saved with fewer ranks: take rank 0's (its RNG is reused)
            engine_file = path / _ENGINE_STATE.format(rank=0)
        engine_state = torch.load(engine_file, weights_only=False)  # our own file: RNG tuples
        with self._temporarily_on_device():
            state = {"model": get_model_state_dict(self.model)}
            if engine_state["has_optimizer_state"]:
                state["optimizer"] = get_optimizer_state_dict(self.model, self.optimizer)
            dcp.load(state, checkpoint_id=str(path / _DCP_DIR))
            set_model_state_dict(self.model, state["model"])
            if engine_state["has_optimizer_state"]:
                set_optimizer_state_dict(self.model, self.optimizer, state["optimizer"])
        self.scheduler.load_state_dict(engine_state["scheduler"])
        self.global_step = engine_state["global_step"]
        restore_rng_state(engine_state["rng"])

    def _barrier(self) -> None:
        if self.device.type == "cuda":
            dist.barrier(device_ids=[self.device.index])
        else:
            dist.barrier()

    def _engine_state(self, has_optimizer_state: bool) -> dict:
        return {
            "global_step": self.global_step,
            "scheduler": self.scheduler.state_dict(),
            "has_optimizer_state": has_optimizer_state,
            "rng": capture_rng_state(),
            "world_size": self.world_size,
        }

    # ------------------------------------------------------------------ device time-sharing

    @property
    def is_offloaded(self) -> bool:
        """True between :meth:`offload` and :meth:`reload`; compute methods refuse to run then."""
        return self._offloaded

    def offload(self) -> None:
        """Move parameter shards, gradients and optimizer state to CPU (no-op on a CPU engine)."""
        if self._offloaded:
            return
        self._move_to(torch.device("cpu"))
        self._offloaded = True

    def reload(self) -> None:
        """Bring everything :meth:`offload` moved back onto the engine's device."""
        if not self._offloaded:
            return
        self._move_to(self.device)
        self._offloaded = False

    def _move_to(self, device: torch.device) -> None:
        if self.device.type == "cpu":
            return
        self.model.to(
            device
        )  # FSDPModule._apply reshards first and re-registers the DTensor shards
        for state in (self.optimizer.state.values() if self.optimizer is not None else ()):
            for key, value in state.items():
                if isinstance(value, torch.Tensor) and value.device != device and key != "step":
                    state[key] = value.to(device, non_blocking=True)
        torch.cuda.synchronize(self.device)
        if device.type == "cpu":
            torch.cuda.empty_cache()

    @contextmanager
    def _temporarily_on_device(self):
        was_offloaded = self._offloaded
        self.reload()
        try:
            yield
        finally:
            if was_offloaded:
                self.offload()

    def _require_on_device(self, what: str) -> None:
        if self._offloaded:
            raise RuntimeError(f"{what}: the engine is offloaded; call reload() first")

    def _require_trainable(self, what: str) -> None:
        if not self.trainable:
            raise RuntimeError(
                f"{what}: this engine is frozen (trainable=False, a reference): it has no optimizer "
                "state to train or checkpoint; rebuild it from the initial weights instead"
            )

    def _require_output(self, output: str, what: str) -> None:
        if self.output != output:
            raise RuntimeError(f"{what}: this engine outputs {self.output}, not {output}")


# ----------------------------------------------------------------------------- helpers


def _check_loss(loss: torch.Tensor) -> None:
    if not isinstance(loss, torch.Tensor) or loss.numel() != 1:
        raise TypeError(
            "loss_fn must return a scalar tensor as its loss, got "
            f"{type(loss).__name__} {tuple(getattr(loss, 'shape', ()))}"
        )
    if not loss.requires_grad:
        raise ValueError("loss_fn returned a loss that does not depend on the log-probs (no grad)")


def _hf_name(name: str) -> str:
    """peft's wrapped name -> the plain HF model's state_dict key."""
    if name.startswith(_PEFT_PREFIX):
        name = name[len(_PEFT_PREFIX) :]
    return name.replace(".base_layer.", ".")
