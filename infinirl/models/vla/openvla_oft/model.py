"""The OpenVLA-OFT network: fused ViTs -> projector -> Llama with parallel decoding of an action chunk.

Sequence (OFT's ``predict_action``), per sample::

    <s>  [image patches ... (+ proprio token)]  prompt tokens ... "▁"  [0 x chunk*action_dim]  </s>

The action positions get *zero* input embeddings and the Llama attends bidirectionally over the
whole sequence (OFT's transformers fork replaces the causal mask by a key-padding mask), so one
forward pass decodes the whole chunk. As in a causal LM, the hidden state *before* each action
token predicts it: the action slice starts at the prompt's last token ("▁"). From that slice:

* the discrete head: the LM head's logits; the last ``n_action_bins`` ids of the tokenizer's
  vocabulary (``vocab_size - 256 .. vocab_size - 1``) are the action tokens, id ``t`` meaning bin
  ``clip(vocab_size - t - 1, 0, 254)`` of 255 bin centres in ``[-1, 1]``;
* the L1 head (:class:`~.heads.L1RegressionHead`): regressed normalised actions.

Batches are right-padded at the end of the sequence (after ``</s>``), so each sample computes
exactly what it computes alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from transformers import LlamaConfig, LlamaForCausalLM

from infinirl.models.vla.openvla_oft.config import OFTConfig
from infinirl.models.vla.openvla_oft.heads import L1RegressionHead, ProprioProjector
from infinirl.models.vla.openvla_oft.vision import FusedVision, Projector

__all__ = ["ActionStates", "OpenVLAOFT", "bin_centers"]


def bin_centers(n_bins: int = 256) -> torch.Tensor:
    """The ``n_bins - 1`` centres of ``n_bins`` evenly spaced edges on ``[-1, 1]`` (float64)."""
    edges = torch.linspace(-1, 1, n_bins, dtype=torch.float64)
    return (edges[:-1] + edges[1:]) / 2


@dataclass
class ActionStates:
    """The LM's last hidden states at the action slice ``[B, chunk * action_dim, H]`` and where the
    sequence lies (for a critic or diagnostics)."""

    hidden: torch.Tensor
    sequence: torch.Tensor  # [B, T, H] last hidden states of the whole sequence
    valid: torch.Tensor  # [B, T] bool


class OpenVLAOFT(nn.Module):
    """Vision, projector, Llama (``LlamaForCausalLM``) and the optional OFT heads."""

    def __init__(self, config: OFTConfig, *, l1_head: bool = False, proprio: bool = False, attention: str = "sdpa"):
        super().__init__()
        self.config = config
        self.vision = FusedVision(config, attention)
        self.projector = Projector(self.vision.width, config.llm_dim, config.fused)
        llama = LlamaConfig(**{k: v for k, v in config.text_config.items() if k not in ("torch_dtype", "dtype")})
        llama._attn_implementation = attention
        self.llm = LlamaForCausalLM(llama)
        platform = config.platform
        self.action_head = L1RegressionHead(config.llm_dim, platform.action_dim) if l1_head else None
        self.proprio_projector = ProprioProjector(platform.proprio_dim, config.llm_dim) if proprio else None

    @property
    def dtype(self) -> torch.dtype:
        return self.projector.fc1.weight.dtype

    def prefix(self, pixel_values: torch.Tensor, proprio: torch.Tensor | None) -> torch.Tensor:
        """Projected patches (+ the proprio token) ``[B, P(+1), H]``."""
        patches = self.projector(self.vision(pixel_values.to(self.dtype)))
        if self.proprio_projector is None:
            return patches
        if proprio is None:
            raise ValueError("this checkpoint has a proprio projector: pass the (normalised) proprio state")
        token = self.proprio_projector(proprio.to(self.dtype).reshape(patches.shape[0], -1))
        return torch.cat([patches, token[:, None]], dim=1)

    def _sequence(self, prefix: torch.Tensor, input_ids: torch.Tensor, lengths: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        embed = self.llm.get_input_embeddings()
        batch, width = prefix.shape[0], prefix.shape[-1]
        count = self.config.num_action_tokens
        stop = embed(torch.full((1,), self.config.stop_token_id, device=input_ids.device))
        tokens = embed(input_ids)
        zeros = torch.zeros(count, width, dtype=prefix.dtype, device=prefix.device)
        rows, starts = [], []
        for b in range(batch):
            n = int(lengths[b])
            rows.append(torch.cat([tokens[b, :1], prefix[b], tokens[b, 1:n], zeros, stop], dim=0))
            starts.append(prefix.shape[1] + n - 1)
        total = max(row.shape[0] for row in rows)
        embeds = prefix.new_zeros(batch, total, width)
        valid = torch.zeros(batch, total, dtype=torch.bool, device=prefix.device)
        for b, row in enumerate(rows):
            embeds[b, :row.shape[0]] = row
            valid[b, :row.shape[0]] = True
        return embeds, valid, torch.as_tensor(starts, device=prefix.device)

    def action_states(self, pixel_values: torch.Tensor, input_ids: torch.Tensor, lengths: torch.Tensor,
                      proprio: torch.Tensor | None = None) -> ActionStates:
        """One bidirectional pass; ``input_ids`` ``[B, L]`` right-padded prompts (``<s>`` first, "▁" last),
        ``lengths`` ``[B]`` their real lengths."""
        prefix = self.prefix(pixel_values, proprio)
        embeds, valid, starts = self._sequence(prefix, input_ids, lengths)
        if embeds.shape[1] > self.config.max_positions:
            raise ValueError(f"sequence of {embeds.shape[1]} tokens exceeds the Llama's max_position_embeddings "
                             f"{self.config.max_positions}: shorten the instruction")
        mask = torch.zeros(valid.shape[0], 1, 1, valid.shape[1], dtype=embeds.dtype, device=embeds.device)
        mask = mask.masked_fill(~valid[:, None, None, :], torch.finfo(embeds.dtype).min)
        mask = mask.expand(-1, 1, valid.shape[1], -1)
        positions = torch.arange(valid.shape[1], device=embeds.device)[None].expand(valid.shape[0], -1)
        sequence = self.llm.model(inputs_embeds=embeds, attention_mask=mask, position_ids=positions,
                                  use_cache=False).last_hidden_state
        index = starts[:, None] + torch.arange(self.config.num_action_tokens, device=embeds.device)[None]
        hidden = torch.gather(sequence, 1, index[..., None].expand(-1, -1, sequence.shape[-1]))
        return ActionStates(hidden=hidden, sequence=sequence, valid=valid)

    def action_logits(self, hidden: torch.Tensor, full_vocab: bool = False) -> torch.Tensor:
        """LM-head logits at the action slice: of the ``n_action_bins`` action tokens ``[B, K*A, 256]``
        (token ``vocab_size - 256 + r`` at index ``r``), or of the whole vocabulary."""
        logits = self.llm.lm_head(hidden)
        if full_vocab:
            return logits
        end = self.config.vocab_size
        return logits[..., end - self.config.n_action_bins:end]

    def token_actions(self, token_ids: torch.Tensor) -> torch.Tensor:
        """Vocabulary ids ``[B, K*A]`` -> normalised actions ``[B, K, A]`` (float64 bin centres)."""
        centers = bin_centers(self.config.n_action_bins).to(token_ids.device)
        bins = (self.config.vocab_size - token_ids - 1).clamp(0, centers.shape[0] - 1)
        return centers[bins].reshape(token_ids.shape[0], -1, self.config.platform.action_dim)

    def slice_to_token(self, index: torch.Tensor) -> torch.Tensor:
        """Index in the action-token slice ``[0, 256)`` -> vocabulary id."""
        return index + (self.config.vocab_size - self.config.n_action_bins)

    def regress(self, hidden: torch.Tensor) -> torch.Tensor:
        if self.action_head is None:
            raise ValueError("no L1 action head loaded: load with head='l1' from a folder holding "
                             "action_head--<step>_checkpoint.pt")
        return self.action_head(hidden)
