"""The KV cache of a decode loop: preallocated per layer, and the per-row state that rides with it."""

from __future__ import annotations

import inspect
from dataclasses import dataclass

import torch
from transformers import DynamicCache
from transformers.cache_utils import DynamicLayer

__all__ = ["DecodeState", "PreallocatedKVLayer", "cache_keyword", "new_kv_cache"]


class PreallocatedKVLayer(DynamicLayer):
    """A KV-cache layer that writes into a buffer sized for the whole generation.

    transformers' ``DynamicLayer`` grows by ``torch.cat``, re-copying the entire cache every
    token, a cost that grows with the batch and the length. The final length is known up front
    (longest prompt + max_new_tokens), so the buffer is allocated once and attention gets a view.
    """

    def __init__(self, capacity: int):
        super().__init__()
        self.capacity = capacity
        self.length = 0
        self._key_buffer: torch.Tensor | None = None
        self._value_buffer: torch.Tensor | None = None

    def lazy_initialization(self, key_states: torch.Tensor, value_states: torch.Tensor) -> None:
        self.dtype, self.device = key_states.dtype, key_states.device
        batch, heads, _, key_dim = key_states.shape
        self._key_buffer = key_states.new_empty((batch, heads, self.capacity, key_dim))
        self._value_buffer = value_states.new_empty(
            (batch, value_states.shape[1], self.capacity, value_states.shape[-1])
        )
        self.is_initialized = True

    def update(self, key_states, value_states, *args, **kwargs):
        if not self.is_initialized:
            self.lazy_initialization(key_states, value_states)
        end = self.length + key_states.shape[-2]
        if end > self.capacity:
            raise RuntimeError(
                f"PreallocatedKVLayer: {end} positions exceed the preallocated {self.capacity}"
            )
        self._key_buffer[:, :, self.length : end] = key_states
        self._value_buffer[:, :, self.length : end] = value_states
        self.length = end
        self._refresh_views()
        return self.keys, self.values

    def _refresh_views(self) -> None:
        self.keys = self._key_buffer[:, :, : self.length]
        self.values = self._value_buffer[:, :, : self.length]

    def get_seq_length(self) -> int:
        return self.length

    def batch_select_indices(self, indices: torch.Tensor) -> None:
        if self.is_initialized:
            self._key_buffer = self._key_buffer[indices]
            self._value_buffer = self._value_buffer[indices]
            self._refresh_views()

    def batch_repeat_interleave(self, repeats: int) -> None:
        if self.is_initialized:
            self._key_buffer = self._key_buffer.repeat_interleave(repeats, dim=0)
            self._value_buffer = self._value_buffer.repeat_interleave(repeats, dim=0)
            self._refresh_views()

    def crop(self, tokens_to_remove: int) -> None:
        if tokens_to_remove > 0:
            raise ValueError(f"crop({tokens_to_remove}): pass a negative number of tokens")
        self.length = max(0, self.length + tokens_to_remove)
        if self.is_initialized:
            self._refresh_views()

    def reset(self) -> None:
        self.length = 0
        self._key_buffer = self._value_buffer = None
        super().reset()


def new_kv_cache(model, capacity: int) -> DynamicCache:
    """A ``DynamicCache`` whose layers are preallocated to ``capacity`` positions, when every layer
    is a plain full-attention one; otherwise (sliding windows, hybrids) transformers' own layers."""
    cache = DynamicCache(config=model.config)
    if cache.layers and all(type(layer) is DynamicLayer for layer in cache.layers):
        cache.layers = [PreallocatedKVLayer(capacity) for _ in cache.layers]
    return cache


@dataclass
class DecodeState:
    """What a micro-batch's decode loop carries between steps, one row per unfinished request."""

    cache: DynamicCache
    attention_mask: torch.Tensor  # [rows, positions so far]; 0 on left padding
    next_position: torch.Tensor  # [rows] position id of the token fed next
    active: torch.Tensor  # [rows] index of each row's request in the micro-batch

    def keep_rows(self, keep: torch.Tensor) -> None:
        """Drop finished rows, so later steps stop computing them."""
        self.cache.batch_select_indices(keep)
        self.attention_mask = self.attention_mask[keep]
        self.next_position = self.next_position[keep]
        self.active = self.active[keep]


def cache_keyword(model) -> str:
    """The name under which ``model``'s forward takes its KV cache.

    transformers 5.2x renamed it ``cache``; ``past_key_values`` still works there but warns on
    every forward call (every decode step of every rank) and is to be removed in 5.40. Older
    releases (we support >= 4.56) know only ``past_key_values``."""
    forward = getattr(model, "_orig_mod", model).forward  # torch.compile's wrapper hides the signature
    return "cache" if "cache" in inspect.signature(forward).parameters else "past_key_values"
