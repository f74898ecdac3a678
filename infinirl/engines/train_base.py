"""What every training engine offers the actor/critic components, and how it is configured.

Components talk to an engine only through :class:`TrainEngine`, so the FSDP2 engine here and any
later backend (Megatron, a plain single-device engine) are swappable by configuration. The config
is a typed dataclass (DESIGN.md §4.1): each field says what it controls and why its default is what
it is, so a YAML file never needs a comment to be understood.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol

import torch
from tensordict import TensorDict

from infinirl.config import bounded

#: ``loss_fn(micro_batch, logprobs, entropy) -> (loss, metrics)``. ``logprobs``/``entropy`` are
#: ``[b, L]`` in the aligned layout of :mod:`infinirl.data.batch` (``entropy`` is ``None`` unless
#: requested; for a value engine the second argument holds the values, see :data:`TrainOutput`).
#: The engine *sums* gradients of ``loss`` over micro-batches and data-parallel ranks, so the loss
#: must already be normalised by a global (whole mini-batch, all ranks) denominator.
LossFn = Callable[
    [TensorDict, torch.Tensor, "torch.Tensor | None"],
    "tuple[torch.Tensor, Mapping[str, float | torch.Tensor]]",
]


#: What a training engine's model outputs per token: log-probs (a policy or a reference policy)
#: or values (a critic: a backbone with a scalar value head).
TrainOutput = Literal["logprobs", "values"]


@dataclass
class LoraSettings:
    """Low-rank adapters (peft ``LoraConfig``). When set, only adapter weights train.

    The exported weights (:meth:`TrainEngine.state_dict_for_sync`) have the adapters merged, so the
    rollout engine loads a plain model with the original parameter names.
    """

    r: int = bounded(8, ge=1)
    """Adapter rank. Larger learns more, costs more memory for optimizer state."""
    alpha: float = bounded(16.0, gt=0)
    """Adapter scaling numerator: the update is ``(alpha / r) * B @ A``."""
    target_modules: list[str] | str = "all-linear"
    """Module names (or peft's ``"all-linear"``) that get adapters; the LM head is never adapted."""
    dropout: float = bounded(0.0, ge=0, lt=1)
    """Dropout on the adapter input. Non-zero makes training log-probs stochastic, which PPO
    ratios then see as noise; keep 0 unless you know you want it."""
    top_layers: int = bounded(0, ge=0)
    """Adapt only the last N decoder layers (0 = all). Backpropagation then stops below the lowest
    adapted layer, so a step costs roughly a forward pass plus N/num_layers of a backward pass:
    the cheapest way to cut trainer time on a CPU when the task needs little capacity."""


@dataclass
class TrainEngineConfig:
    """Optimiser, schedule, batching and precision of a training engine."""

    lr: float = bounded(1e-6, gt=0)
    """Peak learning rate (AdamW). RL fine-tuning of LLMs typically uses 1e-6..1e-5 (LoRA ~1e-4)."""
    weight_decay: float = bounded(0.0, ge=0)
    """Decoupled weight decay (AdamW). 0 by default: RL steps are few and decay pulls weights
    away from the pretrained model that the reference policy also uses."""
    betas: tuple[float, float] = bounded((0.9, 0.999), ge=0, lt=1, each=True)
    """Adam moment decay rates (beta1, beta2), each in [0, 1)."""
    eps: float = bounded(1e-8, gt=0)
    """Adam denominator epsilon."""
    grad_clip: float | None = bounded(1.0, ge=0)
    """Clip the global gradient L2 norm to this value; ``None`` or 0 disables clipping (the norm
    is still computed and reported as ``train/grad_norm``)."""
    warmup_steps: int = bounded(0, ge=0)
    """Linear warmup: step ``s`` (0-based) uses ``lr * min(1, (s + 1) / warmup_steps)``, so the
    first step already moves (an lr of 0 would waste a rollout)."""
    lr_schedule: Literal["constant", "cosine"] = "constant"
    """After warmup: keep ``lr`` (constant) or decay it to ``min_lr_ratio * lr`` at ``total_steps``
    (cosine)."""
    total_steps: int | None = bounded(None, ge=1)
    """Optimizer steps of the whole run; required by the cosine schedule."""
    min_lr_ratio: float = bounded(0.0, ge=0, le=1)
    """Cosine floor, as a fraction of ``lr``."""
    micro_batch_size: int = bounded(4, ge=1)
    """Sequences per forward/backward. Bounds activation memory; results do not depend on it
    (gradients are summed over micro-batches)."""
    score_prompts: bool = False
    """Compute log-probs at prompt positions too. Off (default): when the batch has a
    ``response_mask``, the LM head and its softmax run only from the column before the earliest
    response token, and earlier columns read 0 (RL losses read response tokens only; for a small
    model with a large vocabulary the head is a large share of the FLOPs per token)."""
    share_prompt_prefix: bool = True
    """Pack the rows of a micro-batch that share a prompt into one sequence, ``[prompt | response
    1 | ... | response n]``, with a 4-D attention mask that lets each response see the prompt and
    itself only. A GRPO group then computes its prompt once instead of ``n`` times and no token is
    padding. Exact: same log-probs and gradients to float rounding (see
    :mod:`infinirl.engines.shared_prefix`). Prompt columns read 0. Off with ``score_prompts`` or
    ``activation_checkpointing``, and automatically for sliding-window models; turn it off for a
    model whose attention does not take a prepared 4-D mask the HF way."""
    max_packed_tokens: int = 2048
    """Longest packed row (``share_prompt_prefix``). The packed mask is dense, so attention costs
    the square of a row's length: a group whose prompt plus responses exceed this is packed into
    several rows (each with its own copy of the prompt)."""
    logprob_chunk_tokens: int = 1024
    """Tokens per chunk when turning logits into log-probs: the float32 ``[chunk, vocab]`` block
    is the only full-vocab float32 tensor alive (a 150k vocab at 1024 tokens is ~600 MB)."""
    param_dtype: Literal["auto", "float32", "bfloat16"] = "auto"
    """Compute dtype of forward/backward. Master weights, optimizer state and gradient reduction
    stay float32. ``auto``: bfloat16 on CUDA devices that support it, float32 on CPU. On CPU, bf16
    pays off only with native bf16 matmuls (AVX512_BF16/AMX; see :mod:`infinirl.engines.cpu_dtype`)
    and costs accuracy, so it is opt-in there."""
    lora: LoraSettings | None = None
    """Train low-rank adapters instead of the full model (see :class:`LoraSettings`)."""
    activation_checkpointing: bool = False
    """Recompute each decoder layer's activations in backward: less memory, one more forward pass
    of compute."""
    temperature: float = 1.0
    """Log-probs are computed from ``logits / temperature``, to match the sampling distribution
    of the rollout engine (otherwise the PPO ratio is off even at the same weights)."""
    seed: int = 0
    """Seeds model init (identical on every rank, so shards agree) and later per-rank randomness."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """``auto``: the rank's CUDA device when CUDA is available, else CPU."""

    def __post_init__(self) -> None:
        if self.micro_batch_size < 1:
            raise ValueError(
                f"TrainEngineConfig.micro_batch_size must be >= 1, got {self.micro_batch_size}"
            )
        if self.temperature <= 0:
            raise ValueError(f"TrainEngineConfig.temperature must be > 0, got {self.temperature}")
        if self.max_packed_tokens < 1:
            raise ValueError(f"TrainEngineConfig.max_packed_tokens must be >= 1, got {self.max_packed_tokens}")
        if self.logprob_chunk_tokens < 1:
            raise ValueError("TrainEngineConfig.logprob_chunk_tokens must be >= 1")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(
                "TrainEngineConfig.lr_schedule must be 'constant' or 'cosine', "
                f"got {self.lr_schedule!r}"
            )
        if self.lr_schedule == "cosine" and not self.total_steps:
            raise ValueError(
                "TrainEngineConfig: lr_schedule='cosine' needs total_steps (the decay horizon)"
            )
        if self.param_dtype not in ("auto", "float32", "bfloat16"):
            raise ValueError(
                "TrainEngineConfig.param_dtype must be auto/float32/bfloat16, "
                f"got {self.param_dtype!r}"
            )
        if isinstance(self.lora, Mapping):  # built from YAML/dict
            self.lora = LoraSettings(**self.lora)
        self.betas = tuple(self.betas)  # YAML gives lists


class LrSchedule:
    """Multiplier on the peak lr at optimizer step ``step`` (0-based): warmup, then constant/cosine.

    A class, not a lambda, so ``LambdaLR.state_dict()`` stays picklable and inspectable.
    """

    def __init__(self, cfg: TrainEngineConfig):
        self.warmup_steps = cfg.warmup_steps
        self.kind = cfg.lr_schedule
        self.total_steps = cfg.total_steps
        self.min_lr_ratio = cfg.min_lr_ratio

    def __call__(self, step: int) -> float:
        if self.warmup_steps > 0 and step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        if self.kind == "constant":
            return 1.0
        decay_steps = max(1, self.total_steps - self.warmup_steps)
        progress = min(1.0, (step - self.warmup_steps) / decay_steps)
        cosine = 0.5 * (1.0 + math.cos(math.pi * progress))
        return self.min_lr_ratio + (1.0 - self.min_lr_ratio) * cosine


class TrainEngine(Protocol):
    """The operations an actor or critic component needs from a training backend."""

    def compute_logprobs(
        self, batch: TensorDict, with_entropy: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Aligned ``[B, L]`` log-probs (and entropies) of ``batch['input_ids']``, without grad."""

    def compute_values(self, batch: TensorDict) -> torch.Tensor:
        """Aligned ``[B, L]`` values of ``batch['input_ids']`` (value engines), without grad."""

    def train_step(
        self, batch: TensorDict, loss_fn: LossFn, with_entropy: bool = False
    ) -> dict[str, float]:
        """One optimizer step over this rank's share of a mini-batch; returns metrics."""

    def state_dict_for_sync(
        self, dtype: torch.dtype | None = None, changed_only: bool = False
    ) -> Iterator[tuple[str, torch.Tensor]]:
        """Full (unsharded) weights under the HF model's ``state_dict()`` names, for the rollout;
        ``changed_only``: only those training can change (the receiver holds the rest already)."""

    def save_checkpoint(self, path: str) -> None:
        """Write model, optimizer, scheduler, step and RNG atomically to directory ``path``."""

    def load_checkpoint(self, path: str) -> None:
        """Restore everything :meth:`save_checkpoint` wrote, so training continues exactly."""

    def offload(self) -> None:
        """Move weights, gradients and optimizer state off the accelerator (time-sharing)."""

    def reload(self) -> None:
        """Undo :meth:`offload`."""


__all__ = ["LoraSettings", "LossFn", "LrSchedule", "TrainEngine", "TrainEngineConfig", "TrainOutput"]
