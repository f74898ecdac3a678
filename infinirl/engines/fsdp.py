"""Training engine on FSDP2 (``torch.distributed.fsdp.fully_shard``) over any HF causal LM.

Why FSDP2: parameters are per-parameter ``DTensor`` shards, so frozen and trainable weights (LoRA)
live in the same group, state dicts need no flat-parameter translation, and the same code runs on
one CPU process (gloo, world size 1) and on many GPUs (NCCL).

Data parallelism and the loss contract
--------------------------------------
Every rank gets its own share of a mini-batch. The caller's ``loss_fn`` is normalised by a *global*
denominator (e.g. the number of response tokens in the whole mini-batch over all ranks), so the
gradient of the mini-batch loss is the **sum** of the per-micro-batch, per-rank gradients: the
model is sharded with summed reductions (:mod:`infinirl.engines.sharding`) and micro-batch
gradients simply accumulate, undivided. Ranks with fewer micro-batches than the busiest rank run
zero-loss filler passes (:mod:`infinirl.engines.micro_batches`).

Policies, critics and references
--------------------------------
One engine serves the three model roles of PPO. ``output="logprobs"`` (a causal LM: the actor, or
with ``trainable=False`` a frozen reference) gives per-token log-probs; ``output="values"`` (a
token-classification model with one label: backbone + scalar value head, the critic) gives
per-token values. Both come in the aligned layout of :mod:`infinirl.data.batch`, and the loss
contract, sharding, micro-batching and checkpoints are the same code for all three.

Set-up lives beside the engine: process group, device and dtype in
:mod:`~infinirl.engines.distributed`, the role's HF model in :mod:`~infinirl.engines.model_setup`,
adapters in :mod:`~infinirl.engines.lora`, checkpoint files in :mod:`~infinirl.engines.fsdp_checkpoint`.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager

import torch
import torch.distributed as dist
from tensordict import TensorDict
from torch import nn
from torch.distributed.device_mesh import init_device_mesh
from torch.distributed.fsdp import MixedPrecisionPolicy

from infinirl.algorithms.metrics import MetricReducer
from infinirl.data.batch import ATTENTION_MASK, INPUT_IDS, POSITION_IDS, RESPONSE_MASK
from infinirl.engines.distributed import compute_dtype, init_distributed, resolve_device_type, select_device
from infinirl.engines.fsdp_checkpoint import load_model_and_optimizer, read_engine_state, save_sharded_checkpoint
from infinirl.engines.logprobs import aligned_logprobs, aligned_values
from infinirl.engines.lora import (
    LoraMergePlan,
    apply_lora,
    changing_weight_names,
    lora_merge_plan,
    merged_full_weights,
)
from infinirl.engines.micro_batches import (
    as_tensordict,
    filler_batch,
    first_scored_column,
    micro_batch_plan,
    pad_columns,
    used_width,
)
from infinirl.engines.model_setup import (
    disable_dropout,
    enable_activation_checkpointing,
    pretrained_factory,
    value_head_name,
)
from infinirl.engines.sharding import full_tensor, shard
from infinirl.engines.shared_prefix import pack_by_prompt, packed_logprobs, supports_packed_masks
from infinirl.engines.train_base import LossFn, LrSchedule, TrainEngineConfig, TrainOutput
from infinirl.utils import capture_rng_state, restore_rng_state, seed_everything

__all__ = ["FSDPTrainEngine", "ModelOrFactory", "init_distributed"]

ModelOrFactory = nn.Module | Callable[[], nn.Module]


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
        device_type = resolve_device_type(cfg.device)
        init_distributed(device_type)
        self.rank = dist.get_rank()
        self.world_size = dist.get_world_size()
        self.device = select_device(device_type)
        self.compute_dtype = compute_dtype(cfg.param_dtype, self.device)

        seed_everything(cfg.seed)  # identical init on every rank
        if not isinstance(model, nn.Module):
            model = model()
        model = model.to(device=self.device, dtype=torch.float32)
        # Before LoRA: only the model's own dropout goes; an adapter's (lora.dropout) is the user's choice.
        disable_dropout(model)
        self._packable = supports_packed_masks(getattr(model, "config", None))
        if cfg.activation_checkpointing:
            enable_activation_checkpointing(model)
        self._lora_plan: LoraMergePlan = {}
        if cfg.lora is not None:
            heads = [value_head_name(model)] if output == "values" else None
            model = apply_lora(model, cfg.lora, fully_trained=heads)
            self._lora_plan = lora_merge_plan(model)
        if not trainable:
            model.requires_grad_(False)
        self.mesh = init_device_mesh(self.device.type, (self.world_size,))
        mp_policy = MixedPrecisionPolicy(param_dtype=self.compute_dtype, reduce_dtype=torch.float32)
        self.model = shard(model, mesh=self.mesh, mp_policy=mp_policy)
        self._changing_weights = changing_weight_names(self.model, self._lora_plan)

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
        seed_everything(cfg.seed + self.rank)  # runtime randomness (an adapter's dropout) differs per rank

    @classmethod
    def from_pretrained(
        cls,
        name_or_path: str,
        cfg: TrainEngineConfig,
        output: TrainOutput = "logprobs",
        trainable: bool = True,
        **hf_kwargs,
    ) -> FSDPTrainEngine:
        """Build from an HF checkpoint directory (loaded in float32 on every rank); with
        ``output="values"`` a critic on the checkpoint's backbone
        (:func:`~infinirl.engines.model_setup.pretrained_factory`)."""
        return cls(pretrained_factory(name_or_path, output, **hf_kwargs), cfg, output=output, trainable=trainable)

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
        batch = as_tensordict(batch).to(self.device)
        self.model.eval()
        micro_batches, passes = self._micro_batch_plan(batch)
        logprobs, entropies = [], []
        for index in range(passes):
            if index < len(micro_batches):
                lp, ent = self._forward(micro_batches[index], with_entropy)
                logprobs.append(lp)
                entropies.append(ent)
            else:
                self._forward(filler_batch(self.device), with_entropy=False)
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
        width = used_width(attention_mask)
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
        start = first_scored_column(micro_batch, width) if scored_from else 0
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
            return pad_columns(values, full_width), None
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
        logprobs = pad_columns(logprobs, full_width, left=start)
        return logprobs, (pad_columns(entropy, full_width, left=start) if entropy is not None else None)

    @property
    def _shares_prompt_prefix(self) -> bool:
        """Config only (never the data): every rank must make the same number of model calls."""
        cfg = self.cfg
        return (self.output == "logprobs" and cfg.share_prompt_prefix and not cfg.score_prompts
                and not cfg.activation_checkpointing and self._packable)

    def _micro_batch_plan(self, batch: TensorDict) -> tuple[list[TensorDict], int]:
        return micro_batch_plan(batch, self.cfg.micro_batch_size, self.device)

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

        Returns the loss function's metrics over all micro-batches of all ranks (means, each
        micro-batch weighing the same; a key ending in ``_max`` / ``_min`` their max / min:
        :mod:`infinirl.algorithms.metrics`), plus
        ``train/loss`` (the mini-batch loss: summed, like the gradients), ``train/grad_norm``
        (global, before clipping), ``train/lr`` (used by this step), ``train/skipped_step``
        (1 when the gradient was not finite and the update was skipped) and ``time/train_step``.
        """
        start = time.perf_counter()
        self._require_trainable("train_step")
        self._require_on_device("train_step")
        batch = as_tensordict(batch).to(self.device)
        self.model.train()
        micro_batches, passes = self._micro_batch_plan(batch)
        if passes == 0:
            raise ValueError("train_step: the mini-batch is empty on every rank")
        self.optimizer.zero_grad(set_to_none=True)
        try:
            loss_sum, metric_parts = self._accumulate_gradients(
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
        out = self._combine_metrics(metric_parts)
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
    ) -> tuple[torch.Tensor, MetricReducer]:
        """Forward/backward every micro-batch (plus fillers); FSDP sums their gradients."""
        loss_sum = torch.zeros((), device=self.device)
        metric_parts = MetricReducer()
        for index in range(passes):
            if index < len(micro_batches):
                micro_batch = micro_batches[index]
                logprobs, entropy = self._forward(micro_batch, with_entropy)
                loss, metrics = loss_fn(micro_batch, logprobs, entropy)
                _check_loss(loss)
                metric_parts.add({  # tensors stay on device: no sync per micro-batch
                    key: value.detach().float() if isinstance(value, torch.Tensor) else float(value)
                    for key, value in metrics.items()
                })
                loss_sum += loss.detach().float()
            else:  # filler: joins the collectives, contributes zero gradient
                logprobs, _ = self._forward(filler_batch(self.device), with_entropy=False)
                loss = logprobs.sum() * 0.0
            loss.backward()
        return loss_sum, metric_parts.as_floats()

    def _clip_grad_norm(self) -> torch.Tensor:
        """Global L2 norm of all gradients (sharded ones included); clip to ``cfg.grad_clip``."""
        params = [p for p in self.model.parameters() if p.grad is not None]
        if not params:
            return torch.zeros((), device=self.device)
        total = torch.nn.utils.get_total_norm([p.grad for p in params], norm_type=2.0)
        total = full_tensor(total)  # partial per-shard norms -> the global norm
        if self.cfg.grad_clip and torch.isfinite(total):
            torch.nn.utils.clip_grads_with_norm_(params, self.cfg.grad_clip, total)
        return total

    def _combine_metrics(self, parts: MetricReducer) -> dict[str, float]:
        """Every real micro-batch of every rank: means (each micro-batch weighs the same), and the
        max / min of ``_max`` / ``_min`` keys."""
        gathered: list = [None] * self.world_size
        dist.all_gather_object(gathered, parts)
        combined = MetricReducer()
        for rank_parts in gathered:
            combined.merge(rank_parts)
        return combined.result()

    # ------------------------------------------------------------------ weight export

    def state_dict_for_sync(
        self, dtype: torch.dtype | None = None, changed_only: bool = False
    ) -> Iterator[tuple[str, torch.Tensor]]:
        """Yield ``(name, full tensor)`` per parameter, named like the HF model's ``state_dict()``.

        Gathered on **every** rank (each ``DTensor.full_tensor()`` is an all-gather), one tensor
        at a time so peak memory is one full parameter, which suits bucketed sync. Every rank must
        consume the iterator to the end. LoRA adapters are merged into their base weights and
        their own entries are not yielded. Tensors stay on the engine's device; ``dtype`` casts.
        ``changed_only``: only the weights training can change (the trainable ones, and each LoRA
        layer's merged weight), for a receiver that holds this engine's full export already.
        """
        self._require_on_device("state_dict_for_sync")
        only = self._changing_weights if changed_only else None
        yield from merged_full_weights(self.model.state_dict(), self._lora_plan, dtype, only=only)

    # ------------------------------------------------------------------ checkpoints

    def save_checkpoint(self, path: str | os.PathLike) -> None:
        """Write model + optimizer (DCP shards), scheduler, step and per-rank RNG to ``path``,
        atomically (:func:`~infinirl.engines.fsdp_checkpoint.save_sharded_checkpoint`). With several
        nodes ``path`` must be on a shared filesystem (every rank writes its own shards). Collective.
        """
        self._require_trainable("save_checkpoint")
        with self._temporarily_on_device():
            save_sharded_checkpoint(path, self.model, self.optimizer, self._engine_state, self.rank, self.device)

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Restore a :meth:`save_checkpoint` directory. Collective.

        Model and optimizer reshard to any world size (DCP); each rank restores its own RNG, or
        rank 0's when the checkpoint came from fewer ranks. The lr schedule's position *and* its
        parameters (warmup, horizon) come from the checkpoint, as ``LambdaLR`` stores them.
        """
        self._require_trainable("load_checkpoint")
        engine_state = read_engine_state(path, self.rank)
        with self._temporarily_on_device():
            load_model_and_optimizer(path, self.model, self.optimizer, engine_state["has_optimizer_state"])
        self.scheduler.load_state_dict(engine_state["scheduler"])
        self.global_step = engine_state["global_step"]
        restore_rng_state(engine_state["rng"])

    def _engine_state(self) -> dict:
        return {
            "global_step": self.global_step,
            "scheduler": self.scheduler.state_dict(),
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
