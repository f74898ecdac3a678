"""Walking payloads and boxing their tensors: the structure every transport path shares.

A payload is a tensor, a dict/list/tuple/dataclass/TensorDict of tensors, or any picklable
object. ``walk`` rebuilds it with every tensor replaced; ``box`` replaces tensors by
zero-copy-serialisable boxes (numpy views, CUDA IPC handles) and ``unbox`` undoes it. Used by
``transport`` (channel items), ``p2p`` (point-to-point tensors) and ``weights`` (weight buckets).
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["DTYPE_BY_NAME", "Placeholder", "box", "tensor_bytes", "tensors_in", "unbox", "walk"]

#: every torch dtype by its ``str()`` (e.g. ``"torch.bfloat16"``): dtypes travel as names
DTYPE_BY_NAME = {str(d): d for d in vars(torch).values() if isinstance(d, torch.dtype)}
# numpy has no such dtype: the tensor travels as a view of the same width and is viewed back
_NUMPY_UNSUPPORTED = {torch.bfloat16: torch.int16, torch.float8_e4m3fn: torch.uint8, torch.float8_e5m2: torch.uint8}


@dataclass
class Placeholder:
    """Stands for the ``index``-th tensor of a payload whose data travels separately (p2p)."""

    index: int


@dataclass
class _TensorBox:
    """A CPU tensor as a numpy view (pickled out-of-band by Ray, read back zero-copy)."""

    array: np.ndarray
    dtype: str


@dataclass
class _CudaBox:
    """A CUDA tensor as an IPC handle (rebuilt on the consumer's side of the same GPU)."""

    rebuild: Any
    args: tuple


@dataclass
class _TensorDictBox:
    data: dict
    batch_size: tuple


@dataclass
class _DataclassBox:
    cls: type
    fields: dict


def walk(payload: Any, leaf: Any) -> Any:
    """Rebuild ``payload`` with every tensor replaced by ``leaf(tensor)``; containers are kept.

    The one traversal every path uses (dicts, lists, tuples, dataclasses, TensorDicts), so a new
    container type is supported everywhere at once.
    """
    if isinstance(payload, torch.Tensor):
        return leaf(payload)
    if _is_tensordict(payload):
        return _TensorDictBox({k: walk(v, leaf) for k, v in payload.items()}, tuple(payload.batch_size))
    if isinstance(payload, dict):
        return {k: walk(v, leaf) for k, v in payload.items()}
    if isinstance(payload, list):
        return [walk(v, leaf) for v in payload]
    if isinstance(payload, tuple) and not hasattr(payload, "_fields"):
        return tuple(walk(v, leaf) for v in payload)
    if dataclasses.is_dataclass(payload) and not isinstance(payload, type):
        fields = {f.name: walk(getattr(payload, f.name), leaf) for f in dataclasses.fields(payload)}
        return _DataclassBox(type(payload), fields)
    return payload


def tensors_in(payload: Any) -> list[torch.Tensor]:
    found: list[torch.Tensor] = []
    walk(payload, lambda t: found.append(t))
    return found


def tensor_bytes(payload: Any) -> int:
    """Bytes of array data in a payload (walks containers): torch tensors, numpy arrays and bytes
    objects; used to pick the path (a dict of numpy camera frames is as large as one of tensors)."""
    return sum(t.numel() * t.element_size() for t in tensors_in(payload)) + other_array_bytes(payload)


def other_array_bytes(payload: Any) -> int:
    """Bytes of the numpy arrays and bytes objects in a payload (walks the containers ``walk``
    does): data that only the object store moves without copying it through the channel actor."""
    if isinstance(payload, np.ndarray):
        return payload.nbytes
    if isinstance(payload, (bytes, bytearray)):
        return len(payload)
    if isinstance(payload, memoryview):
        return payload.nbytes
    if isinstance(payload, dict) or _is_tensordict(payload):
        return sum(other_array_bytes(v) for v in payload.values())
    if isinstance(payload, (list, tuple)):
        return sum(other_array_bytes(v) for v in payload)
    if dataclasses.is_dataclass(payload) and not isinstance(payload, type):
        return sum(other_array_bytes(getattr(payload, f.name)) for f in dataclasses.fields(payload))
    return 0


def box(payload: Any, cuda_ipc: bool = False) -> Any:
    """Replace tensors by zero-copy-serialisable boxes, keeping the container structure."""

    def leaf(tensor: torch.Tensor):
        if tensor.is_cuda:
            if cuda_ipc:
                from torch.multiprocessing.reductions import reduce_tensor

                rebuild, args = reduce_tensor(tensor)
                return _CudaBox(rebuild, args)
            tensor = tensor.cpu()
        tensor = tensor.detach().contiguous()
        view_as = _NUMPY_UNSUPPORTED.get(tensor.dtype)
        array = (tensor.view(view_as) if view_as is not None else tensor).numpy()
        return _TensorBox(array, str(tensor.dtype))

    return walk(payload, leaf)


def unbox(payload: Any, leaf: Any = None) -> Any:
    """Inverse of ``box`` (and of ``walk``'s container boxes); ``leaf`` maps ``Placeholder``s."""
    if isinstance(payload, _TensorBox):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # shared-memory arrays are flagged read-only
            tensor = torch.from_numpy(payload.array)
        dtype = DTYPE_BY_NAME[payload.dtype]
        return tensor.view(dtype) if tensor.dtype != dtype else tensor
    if isinstance(payload, _CudaBox):
        return payload.rebuild(*payload.args)
    if leaf is not None and isinstance(payload, Placeholder):
        return leaf(payload)
    if isinstance(payload, _TensorDictBox):
        from tensordict import TensorDict

        return TensorDict({k: unbox(v, leaf) for k, v in payload.data.items()}, batch_size=payload.batch_size)
    if isinstance(payload, _DataclassBox):
        return payload.cls(**{k: unbox(v, leaf) for k, v in payload.fields.items()})
    if isinstance(payload, dict):
        return {k: unbox(v, leaf) for k, v in payload.items()}
    if isinstance(payload, list):
        return [unbox(v, leaf) for v in payload]
    if isinstance(payload, tuple) and not hasattr(payload, "_fields"):
        return tuple(unbox(v, leaf) for v in payload)
    return payload


def _is_tensordict(obj: Any) -> bool:
    return type(obj).__name__ == "TensorDict" and hasattr(obj, "batch_size")
