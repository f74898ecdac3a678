"""The token batch layout shared by rollout, reward, losses and the trainer.

Every per-token tensor is ``[B, L]`` and aligned with ``input_ids``: entry ``t`` describes token
``input_ids[:, t]``. So ``logprobs[:, t] = log p(input_ids[:, t] | input_ids[:, :t])`` and
``response_mask[:, t] = 1`` exactly where ``input_ids[:, t]`` is a generated (response) token: in a
multi-turn (agent) sample, the environment's tokens between the model's turns are part of the
response span but have ``response_mask = 0`` (no loss, KL or entropy on them).
One alignment everywhere means no off-by-one shifts leak between components: the trainer shifts
logits once, internally, and everything downstream reads aligned tensors.

Sequences are packed as ``prompt + response`` with no gap and right-padded to the batch maximum.
Token ids travel end to end (never decoded and re-tokenized), which is why this module takes ids.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict

# Keys of a packed token batch. Sequence-level entries are [B]; token-level entries are [B, L].
INPUT_IDS = "input_ids"
ATTENTION_MASK = "attention_mask"
POSITION_IDS = "position_ids"
RESPONSE_MASK = "response_mask"
ROLLOUT_LOGPROBS = "rollout_logprobs"
PROMPT_LENGTHS = "prompt_lengths"
RESPONSE_LENGTHS = "response_lengths"


def pack_sequences(
    prompt_ids: Sequence[Sequence[int]],
    response_ids: Sequence[Sequence[int]],
    pad_token_id: int,
    response_logprobs: Sequence[Sequence[float]] | None = None,
    response_masks: Sequence[Sequence[int] | None] | None = None,
) -> TensorDict:
    """Pack prompt/response id lists into the aligned, right-padded layout described above.
    ``response_masks[i]`` (one 0/1 per response id, or None for all 1) marks which response ids
    the model sampled; the others (an agent's tool outputs) get ``response_mask = 0``."""
    if len(prompt_ids) != len(response_ids):
        raise ValueError(
            f"pack_sequences: {len(prompt_ids)} prompts but {len(response_ids)} responses; "
            "pass one response per prompt (repeat prompts for n samples)."
        )
    if response_logprobs is not None and len(response_logprobs) != len(response_ids):
        raise ValueError("pack_sequences: response_logprobs must have one entry per response")
    if response_masks is not None and len(response_masks) != len(response_ids):
        raise ValueError("pack_sequences: response_masks must have one entry (or None) per response")
    batch = len(prompt_ids)
    lengths = [len(p) + len(r) for p, r in zip(prompt_ids, response_ids)]
    width = max(lengths) if lengths else 0
    input_ids = torch.full((batch, width), pad_token_id, dtype=torch.long)
    attention = torch.zeros((batch, width), dtype=torch.long)
    response_mask = torch.zeros((batch, width), dtype=torch.float32)
    logprobs = torch.zeros((batch, width), dtype=torch.float32)
    for i, (prompt, response) in enumerate(zip(prompt_ids, response_ids)):
        p, r = len(prompt), len(response)
        if r and response_logprobs is not None and len(response_logprobs[i]) != r:
            raise ValueError(
                f"pack_sequences: sample {i} has {r} response tokens but "
                f"{len(response_logprobs[i])} log-probs"
            )
        input_ids[i, :p] = torch.as_tensor(list(prompt), dtype=torch.long)
        input_ids[i, p : p + r] = torch.as_tensor(list(response), dtype=torch.long)
        attention[i, : p + r] = 1
        response_mask[i, p : p + r] = _sampled(None if response_masks is None else response_masks[i], r, i)
        if response_logprobs is not None and r:
            logprobs[i, p : p + r] = torch.as_tensor(list(response_logprobs[i]), dtype=torch.float32)
    position_ids = (attention.cumsum(dim=1) - 1).clamp(min=0)
    out = {
        INPUT_IDS: input_ids,
        ATTENTION_MASK: attention,
        POSITION_IDS: position_ids,
        RESPONSE_MASK: response_mask,
        PROMPT_LENGTHS: torch.tensor([len(p) for p in prompt_ids], dtype=torch.long),
        RESPONSE_LENGTHS: torch.tensor([len(r) for r in response_ids], dtype=torch.long),
    }
    if response_logprobs is not None:
        out[ROLLOUT_LOGPROBS] = logprobs
    return TensorDict(out, batch_size=[batch])


def _sampled(mask: Sequence[int] | None, length: int, index: int) -> torch.Tensor | float:
    """Sample ``index``'s response mask as a tensor (1.0 when it has none)."""
    if mask is None:
        return 1.0
    if len(mask) != length:
        raise ValueError(f"pack_sequences: sample {index} has {length} response tokens but a response mask of "
                         f"{len(mask)}")
    return torch.as_tensor(list(mask), dtype=torch.float32)
