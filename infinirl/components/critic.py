"""Critic component: the FSDP2 trainer of a value model (HF backbone + scalar value head) for PPO.

The same engine as the actor (:class:`~infinirl.engines.fsdp.FSDPTrainEngine`), in its
``output="values"`` role, with its own optimizer and learning rate. Values are aligned with the
token batch like log-probs are: ``values[:, t]`` is the value of the state in which token ``t`` was
chosen. Like the actor, each rank gets its data-parallel share of a mini-batch plus the *global*
normaliser, so the update does not depend on the number of ranks or the micro-batch size.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from infinirl.algorithms.aggregation import aggregate
from infinirl.algorithms.losses import value_loss
from infinirl.components.engine_worker import EngineWorker
from infinirl.engines.train_base import TrainEngineConfig

#: Batch keys the critic trains on: the values it predicted when the batch was scored (the centre
#: of value clipping) and the regression targets (GAE's lambda-returns).
OLD_VALUES, RETURNS = "values", "returns"

# The engine reports generic train/* metrics; from the critic they must not collide with the actor's.
_RENAMES = {
    "train/loss": "train/value_loss",
    "train/grad_norm": "train/critic_grad_norm",
    "train/lr": "train/critic_lr",
    "train/skipped_step": "train/critic_skipped_step",
    "time/train_step": "time/critic_train_step",
}


def critic_loss(micro_batch: TensorDict, values: torch.Tensor, value_clip: float | None,
                normaliser: float) -> tuple[torch.Tensor, dict]:
    """Clipped value loss of one micro-batch, token-mean over the whole mini-batch (``normaliser``
    = its response-token count), so micro-batches and ranks sum to the mini-batch loss."""
    mask = micro_batch["response_mask"]
    out = value_loss(values=values, old_values=micro_batch[OLD_VALUES], returns=micro_batch[RETURNS],
                     response_mask=mask, clip_range=value_clip)
    loss = aggregate(out.loss_mat, mask, "token-mean", normaliser)
    return loss, {f"train/{k}": float(v) for k, v in out.metrics.items()}


class CriticWorker(EngineWorker):
    def __init__(self, model: str, engine: TrainEngineConfig, value_clip: float | None = None,
                 num_threads: int = 0):
        from infinirl.engines.fsdp import FSDPTrainEngine, init_distributed
        from infinirl.models.hf_causal_lm import resolve_model_source

        if num_threads:
            torch.set_num_threads(num_threads)
        init_distributed("cuda" if self.device == "cuda" else "cpu")
        self.engine = FSDPTrainEngine.from_pretrained(str(resolve_model_source(model)), engine, output="values")
        self.value_clip = value_clip

    def compute_values(self, batch: TensorDict) -> torch.Tensor:
        return self.engine.compute_values(batch)

    def train_step(self, shard: TensorDict, normaliser: float) -> dict:
        """One optimizer step on this rank's share of a mini-batch (``normaliser``: the response
        tokens of the whole mini-batch, all ranks)."""

        def loss_fn(micro, values, _entropy):
            return critic_loss(micro, values, self.value_clip, normaliser)

        metrics = self.engine.train_step(shard, loss_fn)
        return {_RENAMES.get(key, key): value for key, value in metrics.items()}
