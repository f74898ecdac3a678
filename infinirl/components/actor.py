"""Actor component: the FSDP2 trainer of the policy (and, for a LoRA actor, the reference).

Each rank gets its data-parallel share of the mini-batch plus the *global* aggregation
normaliser, so the update equals the single-process update whatever the number of ranks.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from infinirl.algorithms.objective import PolicyObjectiveConfig, policy_objective
from infinirl.components.engine_worker import EngineWorker
from infinirl.engines.train_base import TrainEngineConfig
from infinirl.runtime import WeightSource


class ActorWorker(EngineWorker, WeightSource):
    def __init__(self, model: str, engine: TrainEngineConfig, objective: PolicyObjectiveConfig,
                 num_threads: int = 0, sync_dtype: str | None = None):
        from infinirl.engines.fsdp import FSDPTrainEngine, init_distributed

        if num_threads:
            torch.set_num_threads(num_threads)
        init_distributed("cuda" if self.device == "cuda" else "cpu")
        from infinirl.models.hf_causal_lm import resolve_model_source

        self.engine = FSDPTrainEngine.from_pretrained(str(resolve_model_source(model)), engine)
        self.objective = objective
        self.sync_dtype = getattr(torch, sync_dtype) if sync_dtype else None

    def compute_logprobs(self, batch: TensorDict) -> torch.Tensor:
        logprobs, _ = self.engine.compute_logprobs(batch)
        return logprobs

    def compute_ref_logprobs(self, batch: TensorDict) -> torch.Tensor:
        """Log-probs of the initial policy: a LoRA actor's frozen base with the adapter off."""
        logprobs, _ = self.engine.compute_logprobs(batch, adapter=False)
        return logprobs

    def train_step(self, shard: TensorDict, normaliser: float) -> dict:
        """One optimizer step on this rank's share of a mini-batch.

        ``normaliser`` is the aggregation normaliser of the *whole* mini-batch (all ranks), which
        the driver computes once; summing gradients over micro-batches and ranks is then exact.
        """

        def loss_fn(micro, logprobs, entropy):
            return policy_objective(micro, logprobs, entropy, self.objective, normaliser)

        # The entropy pass costs a [tokens, vocab] softmax: only pay for it when it is used.
        return self.engine.train_step(shard, loss_fn, with_entropy=self.objective.entropy_coef > 0)

    def weights_for_sync(self, changed_only: bool = False):
        if changed_only:
            return self.engine.state_dict_for_sync(dtype=self.sync_dtype, changed_only=True)
        return self.engine.state_dict_for_sync(dtype=self.sync_dtype)
