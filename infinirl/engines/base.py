"""The small interface every inference (rollout) engine implements.

Rollout components talk to this interface only, so the transformers engine used on CPU and the
vLLM/SGLang engines used on GPUs are interchangeable by configuration. It deals in token ids, never
text: multi-turn and agent rollouts keep ids end to end, and decoding then re-tokenizing would
silently change the sequence the trainer scores.

Log-prob convention (read this before writing a loss): ``GenerationResult.response_logprobs[i]`` is
``log softmax(logits / temperature)[response_ids[i]]``, i.e. the log-prob under the *tempered*
policy ``pi(a|s) = softmax(logits / T)``, **without** top-k/top-p truncation. PPO ratios and
truncated importance sampling compare these numbers with the trainer's recomputation, so the trainer
must divide its logits by the same temperature. Top-k/top-p only shape which tokens are *sampled*;
renormalising over the truncated set would make most tokens' log-probs incomparable with the
trainer's full-vocabulary softmax. Greedy decoding has no temperature: it reports ``T = 1``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

import torch

FinishReason = Literal["stop", "length"]


@dataclass(frozen=True)
class SamplingParams:
    """How to sample responses. Defaults are plain ancestral sampling at temperature 1."""

    n: int = 1
    """Samples per prompt (GRPO group size). Results are prompt-major: p0s0, p0s1, ..., p1s0, ..."""
    max_new_tokens: int = 256
    """Hard cap on response length; hitting it gives ``finish_reason == "length"``."""
    temperature: float = 1.0
    """Logits are divided by this before sampling *and* before computing returned log-probs.
    ``0`` means greedy."""
    top_p: float = 1.0
    """Nucleus sampling: sample only from the fewest top tokens whose mass reaches ``top_p``."""
    top_k: int = 0
    """Sample only from the ``top_k`` most likely tokens; ``0`` disables the filter."""
    stop_strings: tuple[str, ...] = ()
    """Stop once the decoded response contains one of these. The token that completes the string is
    kept, like EOS, so the trainer learns to produce it."""
    stop_token_ids: tuple[int, ...] = ()
    """Extra stop tokens on top of the model's EOS ids (kept in the response)."""
    ignore_eos: bool = False
    """Generate past EOS (benchmarks needing a fixed length); explicit stops still apply."""
    seed: int | None = None
    """Same seed + same requests + same engine settings => same samples. ``None`` draws from
    torch's global RNG, so ``torch.manual_seed`` still makes a run reproducible."""
    greedy: bool = False
    """Take the argmax at every step (same as ``temperature=0``)."""

    def __post_init__(self) -> None:
        # Tuples keep the dataclass hashable and immutable even when callers pass lists.
        object.__setattr__(self, "stop_strings", tuple(self.stop_strings))
        object.__setattr__(self, "stop_token_ids", tuple(int(t) for t in self.stop_token_ids))
        if self.n < 1:
            raise ValueError(f"SamplingParams.n={self.n}: need at least one sample per prompt")
        if self.max_new_tokens < 1:
            raise ValueError(
                f"SamplingParams.max_new_tokens={self.max_new_tokens}: must be >= 1"
            )
        if not math.isfinite(self.temperature) or self.temperature < 0:
            raise ValueError(
                f"SamplingParams.temperature={self.temperature}: use a value > 0, or 0 for greedy"
            )
        if not 0.0 < self.top_p <= 1.0:
            raise ValueError(f"SamplingParams.top_p={self.top_p}: must be in (0, 1]; 1 disables it")
        if self.top_k < 0:
            raise ValueError(f"SamplingParams.top_k={self.top_k}: must be >= 0; 0 disables it")
        if any(not s for s in self.stop_strings):
            raise ValueError("SamplingParams.stop_strings: empty string would stop immediately")

    @property
    def is_greedy(self) -> bool:
        return self.greedy or self.temperature == 0.0

    @property
    def logprob_temperature(self) -> float:
        """The ``T`` in ``log softmax(logits / T)`` used for returned log-probs (1 when greedy)."""
        return 1.0 if self.is_greedy else self.temperature


@dataclass
class GenerationResult:
    """One sampled response, in token ids, with what the trainer needs to score it."""

    prompt_ids: list[int]
    response_ids: list[int]
    """Generated ids, truncated after the first stop token / stop string (which is kept)."""
    response_logprobs: list[float]
    """One per response id: ``log softmax(logits / T)`` at that id (see module docstring)."""
    finish_reason: FinishReason
    weight_version: int
    """Version of the weights that generated this sample, for staleness accounting."""
    prompt_index: int = 0
    """Index of the prompt in the request; with ``n > 1`` several results share it."""
    sample_index: int = 0
    """Which of the ``n`` samples of its prompt this is."""
    extra: dict = field(default_factory=dict)
    """Engine-specific details (e.g. which stop string matched); never required by the trainer."""
    response_versions: list[int] | None = None
    """Partial rollouts only: the weights version that sampled each response id (non-decreasing;
    ``weight_version`` is the first one). None: every id came from ``weight_version``."""
    response_mask: list[int] | None = None
    """Multi-turn (agent) rollouts only: 1 where the model sampled the response id, 0 where the
    environment inserted it (a tool's output, the env's text between turns). Inserted ids have
    log-prob 0 and are never trained on. None: every response id was sampled."""

    @property
    def sampled_count(self) -> int:
        """How many response ids the model sampled (all of them unless the env inserted some)."""
        return len(self.response_ids) if self.response_mask is None else sum(self.response_mask)


class InferenceEngine(ABC):
    """Generates token ids from token ids, with versioned weights that the trainer can overwrite."""

    @abstractmethod
    def generate(
        self, prompt_token_ids: list[list[int]], sampling: SamplingParams
    ) -> list[GenerationResult]:
        """Return ``len(prompt_token_ids) * sampling.n`` results, prompt-major
        (prompt 0 samples 0..n-1, then prompt 1, ...)."""

    @abstractmethod
    def load_weights(
        self, named_tensors: Iterable[tuple[str, torch.Tensor]], version: int, changed_only: bool = False
    ) -> None:
        """Overwrite the weights with the trainer's (bit-exact when dtypes match) and tag later
        samples with ``version``. ``named_tensors`` may be a generator, so buckets can stream.
        ``changed_only``: the trainer sends only the weights training changes; allowed once this
        engine has loaded a full set from it (an engine may refuse: it then gets full syncs)."""

    @property
    @abstractmethod
    def weight_version(self) -> int:
        """Version passed to the last successful ``load_weights`` (0 before any sync)."""

    @property
    def context_length(self) -> int | None:
        """Longest prompt + response the engine accepts (``generate`` refuses a prompt whose length
        plus ``max_new_tokens`` exceeds it); None when it sets no limit."""
        return None

    @abstractmethod
    def offload(self) -> None:
        """Free accelerator memory (collocated mode: the trainer runs next). Idempotent."""

    @abstractmethod
    def reload(self) -> None:
        """Undo ``offload``; generation must behave exactly as before it. Idempotent."""

    @property
    @abstractmethod
    def is_offloaded(self) -> bool:
        """True between ``offload()`` and ``reload()``; ``generate`` refuses to run then."""
