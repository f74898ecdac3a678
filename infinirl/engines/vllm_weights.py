"""Which weights a vLLM engine expects, and screening a stream of trainer weights against them."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import torch

__all__ = ["TIED_PAIR", "checkpoint_weight_names", "missing_weights", "screened"]

TIED_PAIR = {"lm_head.weight", "model.embed_tokens.weight"}


def screened(named_tensors, expected: dict[str, tuple[int, ...]] | None, sent: set[str],
              rejected: list[str]) -> Iterator[tuple[str, torch.Tensor]]:
    """Pass on the tensors whose name and shape the checkpoint has; record the others instead of
    raising mid-stream (an exception inside vLLM's layerwise reload would leave layers half
    restored), so ``load_weights`` can report them once the known ones are in."""
    for name, tensor in named_tensors:
        if expected is not None:
            shape = expected.get(name)
            if shape is None and name not in TIED_PAIR:
                rejected.append(f"unknown weight name {name!r}")
                continue
            if shape is not None and tuple(tensor.shape) != shape:
                rejected.append(f"{name!r} has shape {tuple(tensor.shape)}, expected {shape}")
                continue
        sent.add(name)
        yield name, tensor


def missing_weights(expected: dict[str, tuple[int, ...]] | None, sent: set[str]) -> set[str]:
    """The expected names not in ``sent`` (none when the checkpoint could not be listed); either
    name of the tied embedding / LM head pair stands for both."""
    if expected is None:
        return set()
    missing = set(expected) - sent
    if missing & TIED_PAIR and sent & TIED_PAIR:
        missing -= TIED_PAIR
    return missing


def checkpoint_weight_names(source) -> dict[str, tuple[int, ...]] | None:
    """Name -> shape of every tensor in a local safetensors checkpoint (None if not listable)."""
    folder = Path(str(source))
    files = sorted(folder.glob("*.safetensors")) if folder.is_dir() else []
    if not files:
        return None
    from safetensors import safe_open

    shapes: dict[str, tuple[int, ...]] = {}
    for file in files:
        with safe_open(str(file), framework="pt") as handle:
            for name in handle.keys():
                shapes[name] = tuple(handle.get_slice(name).get_shape())
    return shapes
