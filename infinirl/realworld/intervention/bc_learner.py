"""The HG-DAgger learner: the aggregate of human-labelled states, and the policy cloned from it.

:class:`BCLearnerWorker` owns the policy (the same squashed Gaussian actor the robot workers act
with, so its weights load there unchanged), the :class:`~infinirl.realworld.intervention.dagger.AggregateDataset`
and an Adam optimiser. Each iteration the driver hands it the iteration's episodes
(:meth:`aggregate`), it trains ``updates`` mini-batches of :func:`~infinirl.realworld.intervention.dagger.bc_loss`
on the whole aggregate (:meth:`train`) and publishes the result as the next version, which the
driver moves to the robots (it is a :class:`~infinirl.runtime.WeightSource`).

Checkpoints hold the actor, the optimiser, the dataset, the sampling generator and the version.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from infinirl.components.sac_learner import SACNetSpec
from infinirl.realworld.intervention.dagger import AggregateDataset, bc_loss, human_labelled
from infinirl.realworld.robot_worker import VERSION_TENSOR, unit_box
from infinirl.runtime import WeightSource, Worker
from infinirl.utils.atomic import torch_save_atomic

__all__ = ["BCSpec", "BCLearnerWorker"]

_CHECKPOINT = "bc_learner.pt"


@dataclass(frozen=True, kw_only=True)
class BCSpec:
    """Behaviour cloning settings (documented on the runner's config fields)."""

    loss: Literal["mse", "gaussian_nll"] = "mse"
    lr: float = 1e-3
    batch_size: int = 256
    weight_decay: float = 0.0
    seed: int = 0


class BCLearnerWorker(Worker, WeightSource):
    """See the module docstring."""

    def __init__(self, net: SACNetSpec, spec: BCSpec, obs_dim: int, action_dim: int, num_threads: int = 1):
        if num_threads:
            torch.set_num_threads(num_threads)
        torch.manual_seed(spec.seed)
        self.spec = spec
        self.actor = net.build_actor(obs_dim, unit_box(action_dim))
        self.optimizer = torch.optim.Adam(self.actor.parameters(), lr=spec.lr, weight_decay=spec.weight_decay)
        self.dataset = AggregateDataset(obs_dim, action_dim)
        seed = int(np.random.SeedSequence([spec.seed, 0xB0]).generate_state(1)[0])
        self.generator = torch.Generator().manual_seed(seed)
        self.version = 0
        self.updates = 0

    def aggregate(self, episodes: list[dict], all_steps: bool = False) -> dict:
        """Add the human-labelled steps of ``episodes`` (every step with ``all_steps``: demonstrations);
        returns the rows added and the dataset's size."""
        added = 0
        for episode in episodes:
            added += self.dataset.add(*human_labelled(episode, all_steps=all_steps))
        return {"added": added, "size": len(self.dataset)}

    def dataset_size(self) -> int:
        return len(self.dataset)

    def train(self, updates: int) -> dict:
        """``updates`` mini-batches on the aggregate, then publish; returns the mean loss and the version
        (no update and no new version while the dataset is empty)."""
        if not len(self.dataset) or updates < 1:
            return {"loss": float("nan"), "version": self.version, "updates": self.updates, "size": len(self.dataset)}
        self.actor.train()
        total = 0.0
        for _ in range(updates):
            states, actions = self.dataset.sample(self.spec.batch_size, self.generator)
            mean, log_std = self.actor.distribution(states)
            loss = bc_loss(mean, log_std, actions, kind=self.spec.loss)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            total += float(loss.detach())
        self.updates += updates
        self.version += 1
        return {"loss": total / updates, "version": self.version, "updates": self.updates, "size": len(self.dataset)}

    @torch.no_grad()
    def action_error(self, episodes: list[dict]) -> float:
        """Mean squared error of the policy's deterministic action against the human's on the
        human-labelled steps of ``episodes`` (before they are aggregated: held-out)."""
        parts = [human_labelled(e) for e in episodes]
        states = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 1))
        if not len(states):
            return float("nan")
        actions = np.concatenate([p[1] for p in parts])
        mean, _ = self.actor.distribution(torch.from_numpy(states))
        return float(((torch.tanh(mean) - torch.from_numpy(actions)) ** 2).mean())

    def published_version(self) -> int:
        return self.version

    def weights_for_sync(self):
        state = [(name, tensor.detach().clone()) for name, tensor in self.actor.state_dict().items()]
        return [*state, (VERSION_TENSOR, torch.tensor([self.version], dtype=torch.int64))]

    def save_checkpoint(self, path: str) -> None:
        torch_save_atomic({"actor": self.actor.state_dict(), "optimizer": self.optimizer.state_dict(),
                           "dataset": self.dataset.state_dict(), "generator": self.generator.get_state(),
                           "version": self.version, "updates": self.updates}, os.path.join(path, _CHECKPOINT))

    def load_checkpoint(self, path: str) -> None:
        state = torch.load(os.path.join(path, _CHECKPOINT), map_location="cpu", weights_only=False)
        self.actor.load_state_dict(state["actor"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.dataset.load_state_dict(state["dataset"])
        self.generator.set_state(state["generator"])
        self.version, self.updates = int(state["version"]), int(state["updates"])
