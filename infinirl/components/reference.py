"""Reference component: a frozen copy of the initial policy that scores tokens for the KL terms.

It is the actor's engine in its frozen role (``trainable=False``: no optimizer, no gradients), built
from the same weights and with the same compute dtype and temperature as the actor, so at step 0
reference and actor log-probs agree and the KL is 0. Placed like any component (``placement.
reference``), it can shard over its own ranks or sit beside the actor.

A LoRA actor needs none of this: its frozen base model *is* the initial policy, and
``ActorWorker.compute_ref_logprobs`` scores with the adapter switched off (``reference.mode``).
"""

from __future__ import annotations

from dataclasses import replace

import torch
from tensordict import TensorDict

from infinirl.engines.train_base import TrainEngineConfig
from infinirl.runtime import Worker


class ReferenceWorker(Worker):
    def __init__(self, model: str, engine: TrainEngineConfig, num_threads: int = 0):
        from infinirl.engines.fsdp import FSDPTrainEngine, init_distributed
        from infinirl.models.hf_causal_lm import resolve_model_source

        if num_threads:
            torch.set_num_threads(num_threads)
        init_distributed("cuda" if self.device == "cuda" else "cpu")
        # The initial policy: the base weights, no adapters, nothing to recompute in backward.
        frozen = replace(engine, lora=None, activation_checkpointing=False)
        self.engine = FSDPTrainEngine.from_pretrained(str(resolve_model_source(model)), frozen, trainable=False)

    def compute_logprobs(self, batch: TensorDict) -> torch.Tensor:
        logprobs, _ = self.engine.compute_logprobs(batch)
        return logprobs

    def offload(self) -> None:
        self.engine.offload()

    def reload(self) -> None:
        self.engine.reload()
