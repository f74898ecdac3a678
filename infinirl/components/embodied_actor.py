"""Embodied actor: the PPO trainer of a :class:`~infinirl.models.policies.base.Policy`.

The update itself is :func:`infinirl.algorithms.embodied_ppo.ppo_update` (PPO and embodied GRPO);
how the ranks train together is a data-parallel strategy from
:data:`~infinirl.engines.parallel.DATA_PARALLEL` (``actor.strategy``: ``ddp`` or ``fsdp``).

Each rank receives the whole iteration batch (small for state policies; the runner moves it once
through Ray's object store) and trains on *its share of every mini-batch*, whose membership comes
from a generator seeded by ``(seed, iteration)`` (:func:`minibatch_order_generator`): identical on
every rank and on a resumed run. The update is then independent of the number of ranks.

After its epochs the actor folds the batch's observations into the running observation
normaliser (part of the module state, so weight sync and checkpoints carry it), so the statistics
a batch was *collected* with are the ones it is *trained* with.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from infinirl.algorithms import embodied_ppo
from infinirl.algorithms.embodied_ppo import PPOSpec, ppo_minibatch_loss, ppo_objective
from infinirl.components.demo_anchor import DemoAnchor, DemoAnchorSpec
from infinirl.components.embodied_policy import compute_device, critic_lr_of, module_device
from infinirl.components.embodied_rollout import PolicySpec
from infinirl.engines.parallel import DATA_PARALLEL
from infinirl.engines.policy_lora import PolicyLoraSpec, apply_policy_lora, merged_policy_weights
from infinirl.runtime import WeightSource, Worker
from infinirl.utils.memory import peak_memory_bytes
from infinirl.utils.threads import limit_threads

__all__ = ["EmbodiedActorWorker", "PPOSpec", "minibatch_order_generator", "ppo_minibatch_loss",
           "ppo_objective", "ppo_update"]


_CHECKPOINT = "actor.pt"


def minibatch_order_generator(seed: int, iteration: int) -> torch.Generator:
    """The CPU generator that draws an iteration's mini-batch orders: a function of ``(seed,
    iteration)`` only, so every rank and a resumed run draw the same orders."""
    return torch.Generator().manual_seed(int(np.random.default_rng([seed, iteration, 0xB47]).integers(2**62)))


def ppo_update(model, optimizer, batch: dict, iteration: int, ppo: PPOSpec, rank: int = 0, world_size: int = 1,
               all_reduce_grads: Callable[[], None] = lambda: None, anchor: DemoAnchor | None = None) -> dict:
    """:func:`infinirl.algorithms.embodied_ppo.ppo_update` as the actor runs it: mini-batch orders
    from :func:`minibatch_order_generator`, the whole optimizer step compiled (``ppo.compile``)
    where ``ppo.strategy`` allows it, and the behaviour-cloning ``anchor``'s loss in every step."""
    extra = None if anchor is None else (lambda step: anchor.loss(model, iteration, step))
    return embodied_ppo.ppo_update(model, optimizer, batch, iteration, ppo, rank, world_size, all_reduce_grads,
                                   generator=minibatch_order_generator(ppo.seed, iteration),
                                   whole_step=DATA_PARALLEL.get(ppo.strategy).whole_step, anchor=extra)


def _to_tensor(value: Any, device: torch.device | str = "cpu") -> Any:
    """Numpy arrays (nested in dicts) -> tensors on ``device``; anything else is left alone."""
    if isinstance(value, dict):
        return {k: _to_tensor(v, device) for k, v in value.items()}
    if isinstance(value, np.ndarray) and value.dtype.kind in "USO":  # text (instructions) stays as it is
        return value
    if isinstance(value, np.ndarray):  # arrays from Ray's object store are read-only: copy once
        return torch.from_numpy(np.array(value, copy=True)).to(device)
    if isinstance(value, torch.Tensor):
        return value.to(device)
    return value


class EmbodiedActorWorker(Worker, WeightSource):
    """One data-parallel rank of the PPO trainer.

    It computes on the device its placement gives it (``device="auto"``: a GPU rank trains on the
    GPU, with NCCL between ranks) or on the CPU (``device="cpu"``, gloo)."""

    def __init__(self, policy_spec: PolicySpec, observation_spec: dict, action_space, ppo: PPOSpec,
                 num_threads: int = 1, device: str = "auto", lora: PolicyLoraSpec | None = None,
                 anchor: DemoAnchorSpec | None = None):
        # 0: every core this process may run on (actor.num_threads): the on-policy update runs while
        # the envs and the rollout wait, so it may use the cores they leave idle.
        limit_threads(num_threads or len(os.sched_getaffinity(0)))
        self.ppo = ppo
        self.parallel = DATA_PARALLEL.get(ppo.strategy)(self.rank, self.world_size)
        self.compute = compute_device(self.device, device)
        if self.parallel.needs_process_group:
            self.init_process_group("nccl" if self.compute.type == "cuda" else "gloo")
        torch.manual_seed(ppo.seed)  # identical initial weights on every rank
        policy = policy_spec.build(observation_spec, action_space)
        # adapters start at zero (B = 0): the adapted policy acts exactly as the one the rollout built
        self.lora_plan = apply_policy_lora(policy, lora) if lora is not None else None
        self.model = self.parallel.wrap(policy.to(self.compute))
        lr_of = None if ppo.value_lr is None else critic_lr_of(policy, ppo.lr, ppo.value_lr)
        self.optimizer = self.parallel.build_optimizer(self.model, ppo.lr, ppo.adam_eps, lr_of)
        self.anchor = (None if anchor is None else
                       DemoAnchor(anchor, policy.policy.demo_chunk, self.rank, self.world_size))

    def compute_device(self) -> str:
        """Where this rank's policy is (``"cpu"``, ``"cuda:0"``), read off its parameters."""
        return str(module_device(self.model))

    # ---------------------------------------------------------------- training
    def update(self, batch: dict, iteration: int) -> dict:
        """PPO epochs over ``batch`` (flat ``[B, ...]`` arrays, see the runner); returns metrics.

        ``time/actor_update_s`` is the PPO update alone (this rank): the runner's ``time/train_s``
        also holds the advantages, moving the batch here and waiting for the slowest rank."""
        batch = _to_tensor(batch, self.compute)
        self.model.fit_input_stats(batch.get("extras"))  # every rank sees the whole batch: the same statistics
        start = time.perf_counter()
        metrics = ppo_update(self.model, self.optimizer, batch, iteration, self.ppo, self.rank, self.world_size,
                             self._reduce_gradients, self.anchor)
        metrics["time/actor_update_s"] = time.perf_counter() - start
        # after the update, as the observation statistics: the next batch acts and updates with one readout
        metrics.update(self.model.fit_readout(batch["obs"], batch.get("extras")))
        self.model.update_obs_stats({k: batch["obs"][k] for k in self.model.keys})
        metrics["train/num_threads"] = torch.get_num_threads()  # what actor.num_threads resolved to
        metrics["train/peak_memory_bytes"] = peak_memory_bytes(self.compute)  # this rank's
        return metrics

    def _reduce_gradients(self) -> None:
        self.parallel.reduce_gradients(self.model)

    # ---------------------------------------------------------------- weights
    def weights_for_sync(self):
        """The plain policy's weights (with LoRA: each adapter folded into its base weight)."""
        weights = self.parallel.full_weights(self.model)
        return weights if self.lora_plan is None else merged_policy_weights(weights, self.lora_plan)

    def trainable_parameters(self) -> dict[str, int]:
        """Parameters that train and in all (LoRA trains a small part)."""
        return {"trainable": sum(p.numel() for p in self.model.parameters() if p.requires_grad),
                "total": sum(p.numel() for p in self.model.parameters())}

    def weights_digest(self) -> str:
        digest = hashlib.sha256()
        for name, tensor in self.weights_for_sync():
            digest.update(name.encode())
            digest.update(tensor.cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
        return digest.hexdigest()

    def save_checkpoint(self, path: str) -> None:
        """Model (with its observation normaliser) and optimizer, written by rank 0 atomically."""
        self.parallel.save_checkpoint(self.model, self.optimizer, os.path.join(path, _CHECKPOINT))

    def load_checkpoint(self, path: str) -> None:
        self.parallel.load_checkpoint(self.model, self.optimizer, os.path.join(path, _CHECKPOINT), self.compute)
