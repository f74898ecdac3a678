"""Which weights a vLLM engine expects, and screening a stream of trainer weights against them."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

__all__ = ["TIED_PAIR", "checkpoint_weight_names", "missing_weights", "screened"]

TIED_PAIR = {"lm_head.weight", "model.embed_tokens.weight"}

# What vLLM loads, in its order of preference: the HF safetensors checkpoint (the index's shards, or
# the one file), else the PyTorch one. Other files in the folder (Mistral's consolidated.safetensors:
# the same weights under other names) are not loaded, so they are not expected either.
_CHECKPOINTS = (
    ("model.safetensors.index.json", "model.safetensors"),
    ("pytorch_model.bin.index.json", "pytorch_model.bin"),
)


def screened(named_tensors, expected: dict[str, tuple[int, ...]], sent: set[str],
             rejected: list[str]) -> Iterator[tuple[str, torch.Tensor]]:
    """Pass on the tensors whose name and shape the checkpoint has; record the others instead of
    raising mid-stream (an exception inside vLLM's layerwise reload would leave layers half
    restored), so ``load_weights`` can report them once the known ones are in."""
    for name, tensor in named_tensors:
        shape = expected.get(name)
        if shape is None and name not in TIED_PAIR:
            rejected.append(f"unknown weight name {name!r}")
            continue
        if shape is not None and tuple(tensor.shape) != shape:
            rejected.append(f"{name!r} has shape {tuple(tensor.shape)}, expected {shape}")
            continue
        sent.add(name)
        yield name, tensor


def missing_weights(expected: dict[str, tuple[int, ...]], sent: set[str]) -> set[str]:
    """The expected names not in ``sent``; either name of the tied embedding / LM head pair stands
    for both."""
    missing = set(expected) - sent
    if missing & TIED_PAIR and sent & TIED_PAIR:
        missing -= TIED_PAIR
    return missing


def checkpoint_weight_names(source, cache_dir: str | Path | None = None) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every tensor of the checkpoint at ``source`` that vLLM loads: the
    ``weight_map`` of ``model.safetensors.index.json`` when there is one, else ``model.safetensors``;
    then the same for ``pytorch_model.bin``. ``source`` is a local folder, or a hub id read from the
    Hugging Face cache (``cache_dir``; default: the hub's), where vLLM downloaded it.

    Raises ``ValueError`` naming ``source`` when none of these can be read: without the list, a
    sync that left weights out would go unnoticed and the engine would adopt its version.
    """
    find = _file_finder(source, cache_dir)
    for index_name, single_name in _CHECKPOINTS:
        index = find(index_name)
        if index is not None:
            return _indexed_shapes(source, index, find)
        single = find(single_name)
        if single is not None:
            return _file_shapes(single)
    where = "" if Path(str(source)).is_dir() else " in the Hugging Face cache"
    raise ValueError(
        f"VLLMEngine: cannot list the weights of {source}: it has no {', '.join(n for c in _CHECKPOINTS for n in c)}"
        f"{where}, and every weight sync is checked against that list; save the model with save_pretrained "
        "and pass its folder"
    )


def _file_finder(source, cache_dir) -> Callable[[str], Path | None]:
    """``name -> path`` of a file of the checkpoint at ``source`` (None if it has none)."""
    folder = Path(str(source))
    if folder.is_dir():
        return lambda name: folder / name if (folder / name).is_file() else None
    from huggingface_hub import try_to_load_from_cache

    def cached(name: str) -> Path | None:
        path = try_to_load_from_cache(str(source), name, cache_dir=cache_dir)
        return Path(path) if isinstance(path, str) else None  # else not cached, or known absent

    return cached


def _indexed_shapes(source, index: Path, find: Callable[[str], Path | None]) -> dict[str, tuple[int, ...]]:
    try:
        weight_map = json.loads(index.read_text())["weight_map"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"VLLMEngine: cannot list the weights of {source}: {index.name} has no readable "
                         f"weight_map ({exc}); re-save the model with save_pretrained") from None
    shapes: dict[str, tuple[int, ...]] = {}
    for file_name in sorted(set(weight_map.values())):
        shard = find(file_name)
        if shard is None:
            raise ValueError(f"VLLMEngine: cannot list the weights of {source}: {index.name} names {file_name}, "
                             "which is missing; download or save the whole checkpoint")
        listed = {name for name, file in weight_map.items() if file == file_name}
        shapes.update({name: shape for name, shape in _file_shapes(shard).items() if name in listed})
    return shapes


def _file_shapes(file: Path) -> dict[str, tuple[int, ...]]:
    """Name -> shape of the tensors of one checkpoint file, without reading their data."""
    if file.suffix == ".safetensors":
        from safetensors import safe_open

        with safe_open(str(file), framework="pt") as handle:
            return {name: tuple(handle.get_slice(name).get_shape()) for name in handle.keys()}
    state = torch.load(file, map_location="cpu", mmap=True, weights_only=True)  # mapped, not read
    return {name: tuple(tensor.shape) for name, tensor in state.items()}
