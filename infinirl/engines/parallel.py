"""Data-parallel strategies: how one rank's copy of a small model trains together with the others.

A strategy wraps the model, builds its optimizer, sums gradients over ranks, yields the full
weights (for weight sync and digests) and saves/loads checkpoints atomically. Chosen by name from
:data:`DATA_PARALLEL` (``actor.strategy``); a trainer holding one has no branch on the name.

Gradients are *summed* over ranks in every strategy, never averaged: the losses are normalised by
mini-batch-global counts, so the sum is the single-process gradient.

* ``ddp``: every rank holds the whole model; after each backward one flat ``all_reduce(SUM)`` of
  all gradients. Plain modules compile whole (:class:`~infinirl.engines.compiled_step.CompiledAdamStep`).
* ``fsdp``: FSDP2 shards parameters and optimizer state over the ranks
  (:func:`~infinirl.engines.sharding.shard`: reduce-scatter with ``SUM``, in the backward hooks).
  FSDP2's hooks cannot be fused into one compiled step, so only the loss may be compiled.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator

import torch
from torch import nn

from infinirl.engines.compiled_step import CompiledAdamStep
from infinirl.engines.master_weights import adam_for
from infinirl.engines.sharding import full_tensor, shard
from infinirl.registry import Registry
from infinirl.utils.atomic import torch_save_atomic

__all__ = ["DATA_PARALLEL", "DataParallel", "FullyShardedDataParallel", "ReplicatedDataParallel",
           "compiled_whole_step", "param_groups"]


def param_groups(model: nn.Module, lr: float, lr_of: Callable[[str], float] | None = None) -> list[dict]:
    """``model``'s parameters as optimizer groups: one at ``lr`` (``lr_of`` None), else one per
    learning rate ``lr_of(parameter name)`` gives, each keeping it as ``base_lr`` (what a decaying
    schedule scales: a value head may learn faster than the policy it sits on)."""
    if lr_of is None:
        return [{"params": list(model.parameters()), "lr": lr}]
    groups: dict[float, list[nn.Parameter]] = {}
    for name, parameter in model.named_parameters():
        groups.setdefault(float(lr_of(name)), []).append(parameter)
    return [{"params": params, "lr": rate, "base_lr": rate} for rate, params in groups.items()]


def compiled_whole_step(model: nn.Module, optimizer: torch.optim.Optimizer, objective, max_norm: float,
                        all_reduce_grads: Callable[[], None] | None) -> CompiledAdamStep:
    """Forward, loss, backward, clipping and Adam as compiled functions; every step of one update
    has the first step's shapes (equal mini-batches), so later steps skip dynamo's guards."""
    return CompiledAdamStep(model, optimizer, objective, max_norm, all_reduce_grads, fixed_shapes=True)


class DataParallel:
    """One rank (``rank`` of ``world_size``) of a data-parallel strategy; see the module docstring.

    ``whole_step``: the factory of a compiled whole optimizer step for this strategy's models (the
    ``whole_step`` argument of :func:`infinirl.algorithms.embodied_ppo.ppo_update`), or None where
    the model cannot be compiled whole.
    """

    whole_step: Callable[..., CompiledAdamStep] | None = None

    def __init__(self, rank: int = 0, world_size: int = 1):
        self.rank, self.world_size = rank, world_size

    @property
    def needs_process_group(self) -> bool:
        """Whether the ranks must form a torch.distributed group before :meth:`wrap`."""
        return self.world_size > 1

    def wrap(self, model: nn.Module) -> nn.Module:
        """The model as this strategy trains it (built identically on every rank, on its device)."""
        return model

    def build_optimizer(self, model: nn.Module, lr: float, eps: float,
                        lr_of: Callable[[str], float] | None = None) -> torch.optim.Adam:
        """Adam over ``model``'s parameters at ``lr``, or at ``lr_of(name)`` per parameter (see
        :func:`param_groups`); with float32 master weights where trainable ones are bf16/fp16
        (:func:`~infinirl.engines.master_weights.adam_for`)."""
        return adam_for(param_groups(model, lr, lr_of), lr=lr, eps=eps)

    def reduce_gradients(self, model: nn.Module) -> None:
        """Sum every ``p.grad`` over the ranks (after the backward pass, before clipping)."""

    def full_weights(self, model: nn.Module) -> Iterator[tuple[str, torch.Tensor]]:
        """``(name, full tensor)`` of every parameter and buffer; a collective where sharded."""
        for name, tensor in model.state_dict().items():
            yield name, full_tensor(tensor).detach()

    def full_state(self, model: nn.Module, optimizer: torch.optim.Optimizer) -> tuple[dict, dict]:
        """Unsharded model and optimizer state dicts (on every rank; a collective where sharded)."""
        return model.state_dict(), optimizer.state_dict()

    def load_full_state(self, model: nn.Module, optimizer: torch.optim.Optimizer, model_state: dict,
                        optimizer_state: dict) -> None:
        """Load what :meth:`full_state` gave into this rank's (possibly sharded) model and optimizer."""
        model.load_state_dict(model_state)
        optimizer.load_state_dict(optimizer_state)

    def save_checkpoint(self, model: nn.Module, optimizer: torch.optim.Optimizer, file: str | os.PathLike) -> None:
        """Model and optimizer, unsharded, written to ``file`` by rank 0 atomically. Collective."""
        model_state, optimizer_state = self.full_state(model, optimizer)
        if self.rank == 0:
            torch_save_atomic({"model": model_state, "optimizer": optimizer_state}, file)

    def load_checkpoint(self, model: nn.Module, optimizer: torch.optim.Optimizer, file: str | os.PathLike,
                        device: torch.device) -> None:
        """Restore a :meth:`save_checkpoint` file on every rank. Tensors are mapped to ``device``: a
        checkpoint written on a GPU resumes on a CPU-only machine, and vice versa."""
        state = torch.load(file, map_location=device, weights_only=False)
        self.load_full_state(model, optimizer, state["model"], state["optimizer"])


DATA_PARALLEL: Registry[type[DataParallel]] = Registry("data-parallel strategy")


@DATA_PARALLEL.register("ddp")
class ReplicatedDataParallel(DataParallel):
    """Every rank holds the whole model; one flat ``all_reduce(SUM)`` of the gradients per step."""

    whole_step = staticmethod(compiled_whole_step)

    def build_optimizer(self, model: nn.Module, lr: float, eps: float,
                        lr_of: Callable[[str], float] | None = None) -> torch.optim.Adam:
        # Fused Adam: one kernel per step instead of a Python loop over parameters, which matters
        # for a small policy's many small steps.
        return adam_for(param_groups(model, lr, lr_of), lr=lr, eps=eps, fused=True)

    def reduce_gradients(self, model: nn.Module) -> None:
        if self.world_size == 1:
            return
        import torch.distributed as dist

        grads = [p.grad for p in model.parameters() if p.grad is not None]
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat, op=dist.ReduceOp.SUM)
        offset = 0
        for g in grads:
            g.copy_(flat[offset:offset + g.numel()].view_as(g))
            offset += g.numel()


@DATA_PARALLEL.register("fsdp")
class FullyShardedDataParallel(DataParallel):
    """FSDP2: parameters and optimizer state sharded over the ranks, gradients reduce-scattered
    (``SUM``) in the backward hooks, so :meth:`reduce_gradients` has nothing left to do."""

    @property
    def needs_process_group(self) -> bool:
        return True  # FSDP2 needs a group even with one rank

    def wrap(self, model: nn.Module) -> nn.Module:
        return shard(model)

    def full_state(self, model: nn.Module, optimizer: torch.optim.Optimizer) -> tuple[dict, dict]:
        from torch.distributed.checkpoint.state_dict import (
            StateDictOptions,
            get_model_state_dict,
            get_optimizer_state_dict,
        )

        options = StateDictOptions(full_state_dict=True, cpu_offload=True)
        return get_model_state_dict(model, options=options), get_optimizer_state_dict(model, optimizer, options=options)

    def load_full_state(self, model: nn.Module, optimizer: torch.optim.Optimizer, model_state: dict,
                        optimizer_state: dict) -> None:
        from torch.distributed.checkpoint.state_dict import (
            StateDictOptions,
            set_model_state_dict,
            set_optimizer_state_dict,
        )

        options = StateDictOptions(full_state_dict=True)
        set_model_state_dict(model, model_state, options=options)
        set_optimizer_state_dict(model, optimizer, optimizer_state, options=options)
