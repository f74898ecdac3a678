"""Decoder stacks (Gemma or Llama) and their joint ("mixture of transformers") forward, built on
transformers' layers.

π0 runs two decoders side by side: the language model over the prefix (image and language tokens)
and the smaller action expert over the suffix (state and noisy-action tokens). In every layer each
stream projects its own queries, keys and values with its own weights; attention then runs once
over the concatenated sequence under one mask, and each stream takes its slice of the result back
through its own output projection, residuals and MLP. transformers' classes give the pieces
(the attention projections, MLP, RMSNorm, the rotary embedding, ``eager_attention_forward``);
:func:`mixture_forward` is the layer loop they lack.

A stack's *kind* (:data:`STACK_KINDS`, named by its spec's ``kind``) says which transformers
classes build it: ``gemma`` (π0's PaliGemma and expert: ``GemmaRMSNorm`` scales by ``1 + w``,
tanh-GELU MLP, embeddings times ``sqrt(width)``) or ``llama`` (SmolLM2: plain-weight RMSNorm,
SiLU MLP, unscaled embeddings). Both name their weights alike, so the loop is the same for both.

The same loop serves the three passes: prefix alone (its keys/values become the cache), suffix
alone against a cached prefix (each denoising step), and both at once (the training loss).

:class:`AdaptiveRMSNorm` is π0.5's adaRMS (openpi's ``gemma.py``): RMS normalisation whose scale,
shift and residual gate come from the flow time through a ``dense`` layer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from transformers import GemmaConfig, LlamaConfig, PretrainedConfig
from transformers.models.gemma.modeling_gemma import (
    GemmaAttention,
    GemmaMLP,
    GemmaRMSNorm,
    GemmaRotaryEmbedding,
    apply_rotary_pos_emb,
    eager_attention_forward,
)
from transformers.models.llama.modeling_llama import (
    LlamaAttention,
    LlamaMLP,
    LlamaRMSNorm,
    LlamaRotaryEmbedding,
)
from transformers.models.llama.modeling_llama import eager_attention_forward as llama_attention_forward

from infinirl.models.vla.config import GemmaSpec, LlamaSpec
from infinirl.registry import Registry

__all__ = ["STACK_KINDS", "AdaptiveRMSNorm", "DecoderBlock", "DecoderStack", "GemmaStack", "KVCache", "StackKind",
           "Stream", "attention_bias", "block_mask", "gemma_config", "llama_config", "masked_value", "mixture_forward"]


def masked_value(dtype: torch.dtype) -> float:
    """The additive bias of a masked key in ``dtype``: large but finite (as openpi's -2.38e38), so a query
    that may attend nothing (a padding token) gets uniform weights instead of NaNs, which would otherwise
    leak into the cache through 0 * NaN. Half of the most negative value of ``dtype`` or float32, whichever
    is narrower: openpi's constant is -inf in float16 (whose range ends at -65504); the full minimum
    overflows to -inf once a negative score is added to it (half leaves room for any score smaller than
    the other half); and transformers' attention takes the softmax in float32, where float64's minimum
    is -inf."""
    return max(torch.finfo(dtype).min, torch.finfo(torch.float32).min) / 2


class AdaptiveRMSNorm(nn.Module):
    """RMSNorm modulated by a condition: ``(x / rms(x)) * (1 + scale) + shift`` and a residual
    ``gate``, with ``(scale, shift, gate) = dense(cond)``; statistics in float32 like Gemma's."""

    def __init__(self, dim: int, cond_dim: int, eps: float = 1e-6):
        super().__init__()
        self.eps = eps
        self.dense = nn.Linear(cond_dim, 3 * dim)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        variance = x.float().pow(2).mean(-1, keepdim=True)
        normed = x * torch.rsqrt(variance + self.eps)
        modulation = self.dense(cond)
        if x.dim() == 3:
            modulation = modulation.unsqueeze(1)
        scale, shift, gate = modulation.chunk(3, dim=-1)
        out = normed * (1 + scale.float()) + shift.float()
        return out.to(x.dtype), gate.to(x.dtype)


def apply_norm(norm: nn.Module, x: torch.Tensor, cond: torch.Tensor | None):
    """``(normed, gate)``: plain Gemma norms have no gate (a plain residual)."""
    if isinstance(norm, AdaptiveRMSNorm):
        if cond is None:
            raise ValueError("an adaRMS stack needs its condition (the flow-time embedding)")
        return norm(x, cond)
    return norm(x), None


def gated_residual(residual: torch.Tensor, update: torch.Tensor, gate: torch.Tensor | None) -> torch.Tensor:
    return residual + update if gate is None else residual + update * gate


def gemma_config(spec: GemmaSpec, vocab_size: int) -> GemmaConfig:
    """transformers' config for a Gemma of these sizes (tanh-GELU MLP, eps 1e-6, rope theta 1e4)."""
    return GemmaConfig(hidden_size=spec.width, num_hidden_layers=spec.depth, intermediate_size=spec.mlp_dim,
                       num_attention_heads=spec.num_heads, num_key_value_heads=spec.num_kv_heads,
                       head_dim=spec.head_dim, vocab_size=vocab_size, hidden_act="gelu_pytorch_tanh",
                       rms_norm_eps=1e-6)


def llama_config(spec: LlamaSpec, vocab_size: int) -> LlamaConfig:
    """transformers' config for a Llama of these sizes (SiLU MLP, no biases; SmolLM2's layout)."""
    return LlamaConfig(hidden_size=spec.width, num_hidden_layers=spec.depth, intermediate_size=spec.mlp_dim,
                       num_attention_heads=spec.num_heads, num_key_value_heads=spec.num_kv_heads,
                       head_dim=spec.head_dim, vocab_size=vocab_size, hidden_act="silu",
                       rms_norm_eps=spec.rms_norm_eps,
                       rope_parameters={"rope_type": "default", "rope_theta": spec.rope_theta})


@dataclass(frozen=True, kw_only=True)
class StackKind:
    """How to build one kind of decoder stack from transformers' classes.

    ``embed_scale``: Gemma multiplies its token embeddings by ``sqrt(width)`` (part of the model:
    its embedding table was trained for that); Llama does not. ``attend`` is the attention kernel
    the joint loop runs with when the stack comes first (the prefix's kind decides for all)."""

    make_config: Callable[[Any, int], PretrainedConfig]
    attention: type[nn.Module]
    mlp: type[nn.Module]
    norm: type[nn.Module]
    rotary: type[nn.Module]
    attend: Callable
    embed_scale: bool


STACK_KINDS: Registry[StackKind] = Registry("decoder stack kind")
STACK_KINDS.add("gemma", StackKind(make_config=gemma_config, attention=GemmaAttention, mlp=GemmaMLP,
                                   norm=GemmaRMSNorm, rotary=GemmaRotaryEmbedding, attend=eager_attention_forward,
                                   embed_scale=True))
STACK_KINDS.add("llama", StackKind(make_config=llama_config, attention=LlamaAttention, mlp=LlamaMLP,
                                   norm=LlamaRMSNorm, rotary=LlamaRotaryEmbedding,
                                   attend=llama_attention_forward, embed_scale=False))


class DecoderBlock(nn.Module):
    """One decoder layer's weights, named as in transformers' ``GemmaDecoderLayer`` /
    ``LlamaDecoderLayer`` (so in the checkpoints); the forward is :func:`mixture_forward`'s."""

    def __init__(self, kind: StackKind, config: PretrainedConfig, layer_idx: int, cond_dim: int | None):
        super().__init__()
        self.self_attn = kind.attention(config, layer_idx)
        self.mlp = kind.mlp(config)
        width, eps = config.hidden_size, config.rms_norm_eps
        if cond_dim is None:
            self.input_layernorm = kind.norm(width, eps=eps)
            self.post_attention_layernorm = kind.norm(width, eps=eps)
        else:
            self.input_layernorm = AdaptiveRMSNorm(width, cond_dim, eps=eps)
            self.post_attention_layernorm = AdaptiveRMSNorm(width, cond_dim, eps=eps)


class DecoderStack(nn.Module):
    """A decoder's layers and final norm (and token embedding for the VLM; the expert has none),
    of the kind ``spec.kind`` names in :data:`STACK_KINDS`.

    ``cond_dim`` makes every norm adaptive (π0.5's expert)."""

    def __init__(self, spec: GemmaSpec | LlamaSpec, vocab_size: int, embed: bool, cond_dim: int | None = None):
        super().__init__()
        self.spec = spec
        self.kind = STACK_KINDS.get(spec.kind)
        self.config = self.kind.make_config(spec, vocab_size)
        self.embed_tokens = nn.Embedding(vocab_size, spec.width) if embed else None
        self.layers = nn.ModuleList(DecoderBlock(self.kind, self.config, i, cond_dim) for i in range(spec.depth))
        self.norm = (self.kind.norm(spec.width, eps=self.config.rms_norm_eps) if cond_dim is None
                     else AdaptiveRMSNorm(spec.width, cond_dim, eps=self.config.rms_norm_eps))

    def embed(self, tokens: torch.Tensor) -> torch.Tensor:
        """Token embeddings as the stack's first layer expects them (:class:`StackKind`)."""
        embedded = self.embed_tokens(tokens)
        return embedded * math.sqrt(embedded.shape[-1]) if self.kind.embed_scale else embedded

    def rotary_embedding(self) -> nn.Module:
        """The rotary embedding of this stack's config (the joint loop shares the prefix stack's)."""
        return self.kind.rotary(self.config)


GemmaStack = DecoderStack
"""The π0 family's name for a :class:`DecoderStack` (its specs are :class:`GemmaSpec`)."""


@dataclass
class Stream:
    """One stack's tokens in a joint pass: hidden states ``[B, T, W]`` and its adaRMS condition."""

    stack: DecoderStack
    hidden: torch.Tensor
    cond: torch.Tensor | None = None


KVCache = list[tuple[torch.Tensor, torch.Tensor]]


def block_mask(pad_mask: torch.Tensor, blocks: torch.Tensor) -> torch.Tensor:
    """big_vision's prefix-LM mask ``[B, T, T]``: token ``i`` sees valid token ``j`` when
    ``cumsum(blocks)[j] <= cumsum(blocks)[i]``; a 1 in ``blocks`` opens a block that earlier
    tokens cannot see (all zeros: bidirectional; all ones: causal)."""
    cumulative = torch.cumsum(blocks.long(), dim=1)
    visible = cumulative[:, None, :] <= cumulative[:, :, None]
    return visible & (pad_mask[:, None, :] & pad_mask[:, :, None])


def attention_bias(mask: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Boolean ``[B, Q, K]`` -> additive ``[B, 1, Q, K]`` (0 where allowed, :func:`masked_value` elsewhere)."""
    zero = torch.zeros((), dtype=dtype, device=mask.device)
    return torch.where(mask[:, None], zero, torch.tensor(masked_value(dtype), dtype=dtype, device=mask.device))


def _project(layer: DecoderBlock, hidden: torch.Tensor, cond: torch.Tensor | None):
    normed, gate = apply_norm(layer.input_layernorm, hidden, cond)
    shape = (*hidden.shape[:-1], -1, layer.self_attn.head_dim)
    q = layer.self_attn.q_proj(normed).view(shape).transpose(1, 2)
    k = layer.self_attn.k_proj(normed).view(shape).transpose(1, 2)
    v = layer.self_attn.v_proj(normed).view(shape).transpose(1, 2)
    return q, k, v, gate


def _finish(layer: DecoderBlock, hidden: torch.Tensor, attended: torch.Tensor, gate: torch.Tensor | None,
            cond: torch.Tensor | None) -> torch.Tensor:
    hidden = gated_residual(hidden, layer.self_attn.o_proj(attended), gate)
    normed, gate = apply_norm(layer.post_attention_layernorm, hidden, cond)
    return gated_residual(hidden, layer.mlp(normed), gate)


def mixture_forward(streams: Sequence[Stream], bias: torch.Tensor, positions: torch.Tensor,
                    rotary: nn.Module, past: KVCache | None = None,
                    keep_cache: bool = False) -> tuple[list[torch.Tensor], KVCache | None]:
    """Run the streams' stacks layer by layer with joint attention.

    Args:
        streams: the stacks and their tokens, in sequence order (prefix before suffix).
        bias: additive attention bias ``[B, 1, Q, P + Q]`` (``P`` cached tokens, ``Q`` new ones).
        positions: rotary positions ``[B, Q]`` of the new tokens.
        rotary: the rotary embedding (one for all streams: they share ``head_dim``).
        past: per-layer ``(keys, values)`` of ``P`` earlier tokens, attended but not recomputed.
        keep_cache: return this pass's per-layer keys/values (rotated), for later passes.

    Returns:
        each stream's final-normed hidden states, and the cache (None unless ``keep_cache``).
    """
    hidden = [stream.hidden for stream in streams]
    lengths = [h.shape[1] for h in hidden]
    first = streams[0].stack.layers
    attend = streams[0].stack.kind.attend
    cache: KVCache = []
    cos = sin = None
    for index in range(len(first)):
        layers = [stream.stack.layers[index] for stream in streams]
        projected = [_project(layer, h, s.cond) for layer, h, s in zip(layers, hidden, streams, strict=True)]
        q = torch.cat([p[0] for p in projected], dim=2)
        k = torch.cat([p[1] for p in projected], dim=2)
        v = torch.cat([p[2] for p in projected], dim=2)
        if cos is None:
            cos, sin = rotary(q, positions)
        q, k = apply_rotary_pos_emb(q, k, cos, sin)
        if keep_cache:
            cache.append((k, v))
        if past is not None:
            k = torch.cat([past[index][0], k], dim=2)
            v = torch.cat([past[index][1], v], dim=2)
        attention = first[index].self_attn
        attended, _ = attend(attention, q, k, v, bias, attention.scaling)
        attended = attended.reshape(q.shape[0], q.shape[2], -1)
        pieces = attended.split(lengths, dim=1)
        hidden = [_finish(layer, h, piece, p[3], s.cond)
                  for layer, h, piece, p, s in zip(layers, hidden, pieces, projected, streams, strict=True)]
    outputs = [apply_norm(s.stack.norm, h, s.cond)[0] for s, h in zip(streams, hidden, strict=True)]
    return outputs, (cache if keep_cache else None)
