"""PPO's behaviour-cloning anchor: the policy's cloning loss on demonstrations beside the PPO loss.

A policy cloned from a few demonstrations and then fine-tuned with PPO on a handful of episodes
per iteration drifts away from what it imitated faster than the noisy policy gradient improves it.
DAPG (Rajeswaran et al. 2018, "Learning Complex Dexterous Manipulation with Deep Reinforcement
Learning and Demonstrations") keeps a cloning term on the demonstrations in every update, weighed
down as training goes on; this is that term. Every mini-batch step of the PPO update adds
``coef * decay**iteration`` times the policy's :meth:`~infinirl.models.policies.base.Policy.demo_loss`
(for a flow-matching VLA, the same flow-matching loss SFT minimised) on a fresh batch of dataset
frames (:class:`~infinirl.data.demo_frames.DemoFrames`), to the same optimizer step.

Which frames, which image shifts and which flow-matching noise and times a step uses are a function
of ``(seed, iteration, step)`` alone: a resumed run draws them again identically, and the draws never
touch the generators the rest of the update uses. Each data-parallel rank clones its rows of the
batch (drawn whole, then sliced), weighted so that the ranks' gradients sum to the one-rank gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from infinirl.algorithms.embodied_ppo import inner_policy

__all__ = ["DemoAnchor", "DemoAnchorSpec"]


@dataclass(frozen=True, kw_only=True)
class DemoAnchorSpec:
    """The anchor's settings (documented on the runner's ``algorithm.bc`` fields)."""

    data: str
    coef: float
    decay: float = 1.0
    batch_size: int = 32
    augment_shift: int = 0
    camera_key: str | None = None
    seed: int = 0

    def weight(self, iteration: int) -> float:
        """The cloning loss's weight in iteration ``iteration`` (0-based): ``coef * decay**iteration``."""
        return self.coef * self.decay ** iteration


def read_frames(spec: DemoAnchorSpec):
    """The dataset's frames (a LeRobotDatasetError or ConfigError names what is wrong with it)."""
    from infinirl.data.demo_frames import DemoFrames
    from infinirl.data.lerobot_dataset import LeRobotDatasetReader

    return DemoFrames.read(LeRobotDatasetReader(spec.data), spec.camera_key)


class DemoAnchor:
    """The anchor of one actor rank: its frames in memory, and the weighted loss of a step."""

    def __init__(self, spec: DemoAnchorSpec, chunk: int, rank: int = 0, world_size: int = 1, frames=None):
        self.spec, self.chunk = spec, int(chunk)
        self.frames = frames if frames is not None else read_frames(spec)
        size = spec.batch_size
        self.rows = slice(rank * size // world_size, (rank + 1) * size // world_size)
        self.share = (self.rows.stop - self.rows.start) / size

    def generator(self, iteration: int, step: int) -> torch.Generator:
        seed = np.random.default_rng([self.spec.seed, iteration, step, 0xBC]).integers(2**62)
        return torch.Generator().manual_seed(int(seed))

    def batch(self, iteration: int, step: int, policy) -> tuple[dict, torch.Tensor, torch.Tensor, dict]:
        """This rank's rows of step ``step`` of iteration ``iteration``: observations, action chunks,
        their validity, and ``policy``'s draws for them. Everything is drawn for the whole batch and
        then sliced, so the ranks' rows are those one rank would have."""
        generator = self.generator(iteration, step)
        indices = torch.randint(len(self.frames), (self.spec.batch_size,), generator=generator)
        observation, actions, valid = self.frames.batch(indices, self.chunk, self.spec.augment_shift, generator)
        with torch.random.fork_rng(devices=[]):  # drawn on the CPU, whatever device trains
            torch.manual_seed(int(torch.randint(2**62, (1,), generator=generator)))
            draws = policy.demo_draws(self.spec.batch_size)
        rows = self.rows
        observation = {key: value[rows] for key, value in observation.items()}
        return observation, actions[rows], valid[rows], {key: value[rows] for key, value in draws.items()}

    def loss(self, model, iteration: int, step: int) -> tuple[torch.Tensor, dict]:
        """``model``'s weighted cloning loss on this rank's frames of the step, and its metrics
        (the unweighted loss, the weight). ``model`` is the trainer's policy (a ``NormalizedPolicy``,
        possibly sharded): called through ``forward`` with ``demo_mask``."""
        observation, actions, valid, draws = self.batch(iteration, step, inner_policy(model))
        raw = model(observation, actions, draws, demo_mask=valid)
        weight = self.spec.weight(iteration)
        return weight * self.share * raw, {"train/bc_loss": raw.detach(),
                                            "train/bc_weight": torch.tensor(weight, dtype=torch.float64)}

