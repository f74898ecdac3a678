"""Embodied actor: the PPO trainer of a :class:`~infinirl.models.policies.base.Policy`.

The same PPO-clip update serves PPO (GAE advantages, value head trained) and embodied GRPO
(group-normalised episode returns, ``critic=False``: no value loss, and the batch's
``advantage_mask`` drops the decisions after each env's first episode end from every loss term).

Each rank receives the whole iteration batch (small for state policies; the runner moves it once
through Ray's object store) and trains on *its share of every mini-batch*:

* mini-batch membership comes from a generator seeded by ``(seed, iteration)``, identical on every
  rank and on a resumed run;
* per-mini-batch advantage normalisation uses the statistics of the whole mini-batch, and every
  loss term is a sum over this rank's rows divided by a *mini-batch-global* count
  (:func:`~infinirl.algorithms.aggregation.aggregate`), so the summed gradient over ranks equals
  the single-process gradient: the update is independent of the number of ranks (split-invariant);
* gradients are summed over ranks: one flat gloo/NCCL ``all_reduce(SUM)`` per optimizer step
  (``strategy: ddp``), or FSDP2 (``strategy: fsdp``, ``fully_shard`` with SUM reduction and
  ``gradient_divide_factor=1``) which shards parameters and optimizer state over the ranks.

After its epochs the actor folds the batch's observations into the running observation
normaliser (part of the module state, so weight sync and checkpoints carry it), so the statistics
a batch was *collected* with are the ones it is *trained* with.
"""

from __future__ import annotations

import functools
import hashlib
import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from infinirl.algorithms.aggregation import aggregate
from infinirl.algorithms.losses import entropy_loss, ppo_clip_loss, value_loss
from infinirl.components.compiled_step import CompiledAdamStep
from infinirl.components.embodied_policy import compute_device, module_device
from infinirl.components.embodied_rollout import PolicySpec
from infinirl.runtime import WeightSource, Worker
from infinirl.utils.atomic import torch_save_atomic
from infinirl.utils.threads import limit_threads

__all__ = ["EmbodiedActorWorker", "PPOSpec", "actor_process_env", "ppo_minibatch_loss", "ppo_objective",
           "ppo_update"]


def actor_process_env(num_threads: int) -> dict[str, str]:
    """Environment variables an actor rank's process starts with, for ``actor.num_threads``.

    Every worker waits passively in OpenMP (``OMP_WAIT_POLICY=PASSIVE``, see runtime.cluster): a
    thread that finishes a parallel region sleeps at once, so idle processes give the cores back.
    An actor with several threads runs the update's small kernels back to back, and waking a
    sleeping thread for each costs: let its threads spin ~3 ms first (``GOMP_SPINCOUNT``, libgomp's
    own default when no policy is set), then sleep. Measured on 2 cores, the 64x64 pixels CNN's
    update with 2 threads: 5.6-6.3 s passive, 4.2-4.8 s with the spin. Read once, when torch loads
    OpenMP: hence set from the process's start."""
    return {} if num_threads == 1 else {"GOMP_SPINCOUNT": "300000"}


_CHECKPOINT = "actor.pt"


@dataclass(frozen=True, kw_only=True)
class PPOSpec:
    """PPO hyperparameters (documented on the runner's config fields)."""

    lr: float = 3e-4
    anneal_lr: bool = True
    total_iterations: int = 1
    epochs: int = 10
    mini_batches: int = 32
    clip: float = 0.2
    value_clip: float | None = None
    value_coef: float = 0.5
    entropy_coef: float = 0.0
    max_grad_norm: float = 0.5
    normalize_advantages: bool = True
    gae_level: str = "chunk"
    adam_eps: float = 1e-5
    strategy: str = "ddp"
    seed: int = 0
    critic: bool = True
    """Train the value head (PPO). False (GRPO): no value loss is computed, the head stays as built."""
    compile: bool = False
    """Compile each mini-batch's optimizer step (:class:`~infinirl.components.compiled_step.CompiledAdamStep`;
    under FSDP2 only the forward pass and loss, :func:`_minibatch_loss`)."""


def _to_tensor(value: Any, device: torch.device | str = "cpu") -> Any:
    """Numpy arrays (nested in dicts) -> tensors on ``device``; anything else is left alone."""
    if isinstance(value, dict):
        return {k: _to_tensor(v, device) for k, v in value.items()}
    if isinstance(value, np.ndarray):  # arrays from Ray's object store are read-only: copy once
        return torch.from_numpy(np.array(value, copy=True)).to(device)
    if isinstance(value, torch.Tensor):
        return value.to(device)
    return value


def _rows(value: Any, index: torch.Tensor) -> Any:
    if isinstance(value, dict):
        return {k: _rows(v, index) for k, v in value.items()}
    return value[index]


class EmbodiedActorWorker(Worker, WeightSource):
    """One data-parallel rank of the PPO trainer.

    It computes on the device its placement gives it (``device="auto"``: a GPU rank trains on the
    GPU, with NCCL between ranks) or on the CPU (``device="cpu"``, gloo)."""

    def __init__(self, policy_spec: PolicySpec, observation_spec: dict, action_space, ppo: PPOSpec,
                 num_threads: int = 1, device: str = "auto"):
        # 0: every core this process may run on (actor.num_threads): the on-policy update runs while
        # the envs and the rollout wait, so it may use the cores they leave idle.
        limit_threads(num_threads or len(os.sched_getaffinity(0)))
        if ppo.strategy not in ("ddp", "fsdp"):
            raise ValueError(f"actor strategy must be 'ddp' or 'fsdp', got {ppo.strategy!r}")
        self.ppo = ppo
        self.compute = compute_device(self.device, device)
        self.distributed = self.world_size > 1 or ppo.strategy == "fsdp"
        if self.distributed:
            self.init_process_group("nccl" if self.compute.type == "cuda" else "gloo")
        torch.manual_seed(ppo.seed)  # identical initial weights on every rank
        self.model = policy_spec.build(observation_spec, action_space).to(self.compute)
        if ppo.strategy == "fsdp":
            from torch.distributed.fsdp import FSDPModule, fully_shard

            fully_shard(self.model)
            for module in self.model.modules():
                if isinstance(module, FSDPModule):
                    module.set_gradient_divide_factor(1.0)
                    module.set_force_sum_reduction_for_comms(True)
        # Fused Adam: one kernel per step instead of a Python loop over parameters (~20% of a small
        # policy's update on CPU). FSDP2's DTensor parameters take the default implementation.
        fused = {"fused": True} if ppo.strategy == "ddp" else {}
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=ppo.lr, eps=ppo.adam_eps, **fused)

    def compute_device(self) -> str:
        """Where this rank's policy is (``"cpu"``, ``"cuda:0"``), read off its parameters."""
        return str(module_device(self.model))

    # ---------------------------------------------------------------- training
    def update(self, batch: dict, iteration: int) -> dict:
        """PPO epochs over ``batch`` (flat ``[B, ...]`` arrays, see the runner); returns metrics.

        ``time/actor_update_s`` is the PPO update alone (this rank): the runner's ``time/train_s``
        also holds the advantages, moving the batch here and waiting for the slowest rank."""
        batch = _to_tensor(batch, self.compute)
        start = time.perf_counter()
        metrics = ppo_update(self.model, self.optimizer, batch, iteration, self.ppo,
                             self.rank, self.world_size, self._all_reduce_grads)
        metrics["time/actor_update_s"] = time.perf_counter() - start
        self.model.update_obs_stats({k: batch["obs"][k] for k in self.model.keys})
        metrics["train/num_threads"] = torch.get_num_threads()  # what actor.num_threads resolved to
        return metrics

    def _all_reduce_grads(self) -> None:
        if not self.distributed or self.ppo.strategy == "fsdp":
            return  # FSDP2 reduce-scatters (SUM) in its backward hooks
        import torch.distributed as dist

        grads = [p.grad for p in self.model.parameters() if p.grad is not None]
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat, op=dist.ReduceOp.SUM)
        offset = 0
        for g in grads:
            g.copy_(flat[offset:offset + g.numel()].view_as(g))
            offset += g.numel()

    # ---------------------------------------------------------------- weights
    def _named_full(self):
        """(name, full tensor) of every parameter and buffer; a collective under FSDP2."""
        from torch.distributed.tensor import DTensor

        for name, tensor in self.model.state_dict().items():
            if isinstance(tensor, DTensor):
                tensor = tensor.full_tensor()
            yield name, tensor.detach()

    def weights_for_sync(self):
        return self._named_full()

    def weights_digest(self) -> str:
        digest = hashlib.sha256()
        for name, tensor in self._named_full():
            digest.update(name.encode())
            digest.update(tensor.cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
        return digest.hexdigest()

    def save_checkpoint(self, path: str) -> None:
        """Model (with its observation normaliser) and optimizer, written by rank 0 atomically."""
        if self.ppo.strategy == "fsdp":
            from torch.distributed.checkpoint.state_dict import (
                StateDictOptions,
                get_model_state_dict,
                get_optimizer_state_dict,
            )

            options = StateDictOptions(full_state_dict=True, cpu_offload=True)
            model_state = get_model_state_dict(self.model, options=options)
            optim_state = get_optimizer_state_dict(self.model, self.optimizer, options=options)
        else:
            model_state, optim_state = self.model.state_dict(), self.optimizer.state_dict()
        if self.rank != 0:
            return
        torch_save_atomic({"model": model_state, "optimizer": optim_state}, os.path.join(path, _CHECKPOINT))

    def load_checkpoint(self, path: str) -> None:
        # map_location: a checkpoint written on a GPU resumes on a CPU-only machine, and vice versa
        state = torch.load(os.path.join(path, _CHECKPOINT), map_location=self.compute, weights_only=False)
        if self.ppo.strategy == "fsdp":
            from torch.distributed.checkpoint.state_dict import (
                StateDictOptions,
                set_model_state_dict,
                set_optimizer_state_dict,
            )

            options = StateDictOptions(full_state_dict=True)
            set_model_state_dict(self.model, state["model"], options=options)
            set_optimizer_state_dict(self.model, self.optimizer, state["optimizer"], options=options)
        else:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])


def ppo_update(model, optimizer, batch: dict, iteration: int, ppo: PPOSpec, rank: int = 0, world_size: int = 1,
               all_reduce_grads=lambda: None) -> dict:
    """The PPO epochs of one iteration on ``model`` (a ``NormalizedPolicy``, possibly FSDP2-wrapped).

    ``batch`` (tensors, flat over ``B = T * N`` decisions): ``obs`` dict, ``actions``
    ``[B, C, ...]``, ``logprobs`` / ``step_mask`` ``[B, C]``, ``values`` ``[B]``, ``advantages`` /
    ``returns`` ``[B]`` (chunk level) or ``[B, C]`` (action level), optional ``extras``, optional
    ``advantage_mask`` shaped like ``advantages`` (the estimator's mask; all true if absent):
    decisions outside it count in no loss term and in no normaliser (policy loss, entropy,
    per-mini-batch advantage statistics).
    """
    if ppo.anneal_lr:
        lr = ppo.lr * max(0.0, 1.0 - iteration / max(1, ppo.total_iterations))
        for group in optimizer.param_groups:
            group["lr"] = lr
    size = batch["actions"].shape[0]
    per_mini = size // ppo.mini_batches
    generator = torch.Generator().manual_seed(int(np.random.default_rng([ppo.seed, iteration, 0xB47]).integers(2**62)))
    device = batch["advantages"].device
    keep_all = (batch["advantage_mask"].to(torch.float32) if "advantage_mask" in batch
                else torch.ones(batch["advantages"].shape, dtype=torch.float32, device=device))
    params = [p for p in model.parameters() if p.requires_grad]
    minibatch_loss = _minibatch_loss(ppo.compile)
    # actor.compile on a plain (non-FSDP) model: the whole optimizer step is one compiled function;
    # under FSDP2 (whose hooks dynamo cannot fuse into it) only the mini-batch loss is compiled.
    whole_step = (CompiledAdamStep(model, optimizer, _objective_of_outputs, ppo.max_grad_norm,
                                   all_reduce_grads if world_size > 1 else None, fixed_shapes=True)
                  if ppo.compile and ppo.strategy != "fsdp" else None)
    step_metrics: dict[str, list[torch.Tensor]] = {}
    # The observation statistics are fixed during the update (folded in after it): normalise the
    # whole batch once instead of every mini-batch (identical values, fewer small ops per step).
    normalize = getattr(model, "normalize", None)
    obs = normalize(batch["obs"]) if normalize is not None else batch["obs"]
    columns = {"obs": obs, "actions": batch["actions"], "logprobs": batch["logprobs"],
               "values": batch["values"], "returns": batch["returns"],
               "advantages": batch["advantages"].to(torch.float32), "keep": keep_all,
               "step_mask": batch["step_mask"].to(torch.float32)}
    if "extras" in batch:
        columns["extras"] = batch["extras"]
    for _ in range(ppo.epochs):
        order = torch.randperm(size, generator=generator).to(device)  # drawn on CPU: same order on any device
        # One gather per epoch; each mini-batch is then a slice (a view), not a gather per tensor.
        shuffled = _rows(columns, order)
        for m in range(ppo.mini_batches):
            start = m * per_mini
            mine = slice(start + rank * per_mini // world_size, start + (rank + 1) * per_mini // world_size)
            whole = {key: shuffled[key][start:start + per_mini] for key in ("advantages", "keep", "step_mask")}
            rows = {key: shuffled[key][mine] for key in ("logprobs", "values", "returns")}
            model_args = (_rows(shuffled["obs"], mine), shuffled["actions"][mine],
                          _rows(shuffled["extras"], mine) if "extras" in shuffled else None, True,
                          normalize is not None)
            if whole_step is not None:
                _, metrics, grad_norm = whole_step.step(model_args, (ppo, rank, world_size, whole, rows))
            else:
                loss, metrics = minibatch_loss(model, ppo, rank, world_size, model_args, whole, rows)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                all_reduce_grads()
                grad_norm = torch.nn.utils.clip_grad_norm_(params, ppo.max_grad_norm, foreach=True)
                if hasattr(grad_norm, "full_tensor"):
                    grad_norm = grad_norm.full_tensor()
                optimizer.step()
            metrics["train/grad_norm"] = grad_norm.detach()
            # Kept as tensors and averaged once after the loop: no per-step conversion to Python floats.
            for key, value in metrics.items():
                step_metrics.setdefault(key, []).append(value)
    # The rollout-vs-trainer log-prob mismatch is that of the first mini-batch, before any step.
    mismatch = step_metrics.pop("train/logprob_mismatch", [torch.zeros(())])[0]
    metrics = {key: float(torch.stack(values).to(torch.float64).mean()) for key, values in step_metrics.items()}
    if ppo.critic:
        returns = batch["returns"][:, 0] if ppo.gae_level == "action" else batch["returns"]
        variance = float(returns.var())
        metrics["train/explained_variance"] = (float("nan") if variance == 0
                                               else 1.0 - float((returns - batch["values"]).var()) / variance)
    metrics["train/lr"] = optimizer.param_groups[0]["lr"]
    metrics["train/logprob_mismatch"] = float(mismatch)
    metrics["train/optimizer_steps"] = ppo.epochs * ppo.mini_batches
    return metrics


def ppo_objective(ppo: PPOSpec, rank: int, world_size: int, logprobs: torch.Tensor, entropy: torch.Tensor | None,
                  values: torch.Tensor, whole: dict, mine: dict) -> tuple[torch.Tensor, dict]:
    """This rank's loss on one mini-batch and its detached metrics (tensors).

    ``logprobs`` / ``entropy`` ``[m, C]`` and ``values`` ``[m]`` are the model's outputs on this
    rank's rows; ``mine`` holds the same rows' ``logprobs`` (old), ``values`` (old) and ``returns``;
    ``whole`` holds ``advantages``, ``keep`` and ``step_mask`` of the *whole* mini-batch (all
    ranks), whose statistics and counts every rank shares: advantage normalisation and every
    loss normaliser are mini-batch-global, so the ranks' gradients sum to the 1-rank gradient.

    A pure function of tensors (no Python number read back from them, no branch on their values),
    so ``torch.compile`` takes it whole, without graph breaks (``actor.compile``).
    """
    action_level = ppo.gae_level == "action"
    adv, keep = whole["advantages"], whole["keep"]  # [M] chunk level, [M, C] action level
    # mask: executed actions to train on [M, C]; weights: the policy-loss rows ([M] or [M, C])
    mask = whole["step_mask"] * (keep if action_level else keep[:, None])
    weights = mask if action_level else keep
    if ppo.normalize_advantages:  # statistics of the whole mini-batch (all ranks)
        count = weights.sum()
        mean = (adv * weights).sum() / count.clamp(min=1)
        std = torch.sqrt(((adv - mean) ** 2 * weights).sum() / (count - 1).clamp(min=1))
        adv = (adv - mean) / (std + 1e-8)
    n_pg, n_entropy, n_value = weights.sum(), mask.sum(), float(adv.shape[0])
    size = adv.shape[0]
    share = slice(rank * size // world_size, (rank + 1) * size // world_size)
    adv, mask, weights = adv[share], mask[share], weights[share]
    old = mine["logprobs"]
    metrics = {"train/logprob_mismatch": ((logprobs.detach() - old).abs() * mask).sum() / mask.sum().clamp(min=1)}
    if action_level:
        pg = ppo_clip_loss(logprobs=logprobs, old_logprobs=old, advantages=adv, response_mask=weights,
                           clip_low=ppo.clip)
        returns = mine["returns"][:, 0]
    else:
        pg = ppo_clip_loss(logprobs=(logprobs * mask).sum(-1), old_logprobs=(old * mask).sum(-1),
                           advantages=adv, response_mask=weights, clip_low=ppo.clip)
        returns = mine["returns"]
    loss = pg_loss = aggregate(pg.loss_mat, weights, "token-mean", n_pg)
    metrics.update({"train/policy_loss": pg_loss.detach(), "train/approx_kl": pg.metrics["approx_kl"],
                    "train/clip_fraction": pg.metrics["clip_fraction"]})
    if ppo.critic:
        ones = torch.ones_like(returns)
        vl = value_loss(values=values, old_values=mine["values"], returns=returns.to(values.dtype),
                        response_mask=ones, clip_range=ppo.value_clip)
        loss = pg_loss + ppo.value_coef * aggregate(vl.loss_mat, ones, "token-mean", n_value)
        metrics["train/value_loss"] = vl.metrics["value_mse"] / 2
    if entropy is not None:
        ent = entropy_loss(mask, entropy=entropy)
        metrics["train/entropy"] = ent.metrics["entropy"]
        if ppo.entropy_coef:
            loss = loss + ppo.entropy_coef * aggregate(ent.loss_mat, mask, "token-mean", n_entropy)
    return loss, metrics


def ppo_minibatch_loss(model, ppo: PPOSpec, rank: int, world_size: int, model_args: tuple, whole: dict,
                       mine: dict) -> tuple[torch.Tensor, dict]:
    """The policy's forward pass on this rank's rows of a mini-batch (``model_args``: observations,
    actions, extras, with_entropy, obs_normalized), then :func:`ppo_objective`."""
    return _objective_of_outputs(*model(*model_args), ppo, rank, world_size, whole, mine)


def _objective_of_outputs(logprobs, entropy, values, ppo: PPOSpec, rank: int, world_size: int, whole: dict,
                          mine: dict) -> tuple[torch.Tensor, dict]:
    """:func:`ppo_objective` with the model's outputs first (the compiled step's objective contract)."""
    return ppo_objective(ppo, rank, world_size, logprobs, entropy, values, whole, mine)


@functools.cache
def _minibatch_loss(compile_: bool):
    """:func:`ppo_minibatch_loss`, compiled once per process when ``actor.compile`` asks for it
    (the FSDP2 path; a plain model compiles its whole step, :mod:`~infinirl.components.compiled_step`).

    Why: a small policy's mini-batch step is hundreds of tiny ops, each paying the eager
    per-op (and autograd-node) overhead; on CPU that overhead, not arithmetic, is most of the
    update (``benchmarks/embodied_pipeline.py``). Compiled, the forward pass and the loss and their
    backward become a few fused kernels. ``dynamic=False``: mini-batch shapes never change within a
    run. The optimizer step and gradient clipping stay eager (already fused / foreach kernels).
    """
    if not compile_:
        return ppo_minibatch_loss
    return torch.compile(ppo_minibatch_loss, dynamic=False)
