"""Moving payloads between processes by the cheapest path, with only metadata through queues.

``pack(payload)`` returns an ``Envelope``, small and cheap to send through a channel's queue;
``unpack(envelope)`` returns the payload in the consumer. The path is chosen per payload:

- **inline**: small payloads (< ``INLINE_LIMIT_BYTES`` of tensor data) ride inside the envelope, as
  Ray itself inlines small task arguments: one RPC, no object-store round trip.
- **local**: producer and consumer are the same process: the object is handed over by reference.
- **object store**: CPU tensors are flattened to numpy views and ``ray.put`` once; a consumer on
  the same node maps them from shared memory with zero copies, another node pulls them directly
  from the producer's node. (Pickling ``torch.Tensor`` through Ray copies and is ~8x slower for
  64 MB than a numpy view: that is why tensors are boxed here.)
- **cuda_ipc**: CUDA tensors travel as CUDA IPC handles when the consumer sees the same GPU; the
  producer keeps them alive until the consumer has rebuilt them.

Payloads may be tensors, dicts/lists/tuples/dataclasses/TensorDicts of tensors, or any picklable
object. Delivered tensors are zero-copy views: each channel item reaches exactly one consumer, so
that consumer may modify them in place.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import threading
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import ray
import torch

INLINE_LIMIT_BYTES = 64 * 1024

_NUMPY_UNSUPPORTED = {torch.bfloat16: torch.int16, torch.float8_e4m3fn: torch.uint8, torch.float8_e5m2: torch.uint8}
_DTYPE_BY_NAME = {str(d): d for d in vars(torch).values() if isinstance(d, torch.dtype)}

_local_items: dict[int, Any] = {}
_local_lock = threading.Lock()
_ids = itertools.count()


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


@dataclass
class Envelope:
    """What a channel queue holds: the path taken, the producer, and a ref or the inline payload."""

    path: str
    producer_pid: int
    producer_node: str
    body: Any = None
    local_id: int | None = None
    nbytes: int = 0


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
        return _DataclassBox(type(payload), {f.name: walk(getattr(payload, f.name), leaf) for f in dataclasses.fields(payload)})
    return payload


def tensors_in(payload: Any) -> list[torch.Tensor]:
    found: list[torch.Tensor] = []
    walk(payload, lambda t: found.append(t))
    return found


def tensor_bytes(payload: Any) -> int:
    """Bytes of tensor data in a payload (walks containers); used to pick the path."""
    if isinstance(payload, np.ndarray):
        return payload.nbytes
    return sum(t.numel() * t.element_size() for t in tensors_in(payload))


def _has_cuda(payload: Any) -> bool:
    return any(t.is_cuda for t in tensors_in(payload))


def _node_id() -> str:
    try:
        return ray.get_runtime_context().get_node_id() if ray.is_initialized() else "local"
    except Exception:
        return "local"


def pack(payload: Any, same_process: bool = False, force_p2p: bool = False) -> Envelope:
    """Wrap ``payload`` for a queue. ``same_process``: every consumer is this process.
    ``force_p2p``: send tensors point-to-point (a channel created with ``transport="p2p"``)."""
    from infinirl.runtime import p2p

    pid, node = os.getpid(), _node_id()
    if same_process:
        local_id = next(_ids)
        with _local_lock:
            _local_items[local_id] = payload
        return Envelope("local", pid, node, local_id=local_id)
    nbytes = tensor_bytes(payload)
    if force_p2p and p2p.available() and nbytes:
        return Envelope("p2p", pid, node, body=p2p.offer(payload), nbytes=nbytes)
    if _has_cuda(payload):
        if p2p.available():  # consumer decides: CUDA IPC on our GPU, NCCL from any other
            return Envelope("p2p", pid, node, body=p2p.offer(payload, with_ipc=True), nbytes=nbytes)
        return Envelope("cuda_ipc", pid, node, body=box(payload, cuda_ipc=True), nbytes=nbytes)
    if nbytes < INLINE_LIMIT_BYTES:
        return Envelope("inline", pid, node, body=payload, nbytes=nbytes)
    # The ref sits in a list so Ray passes it as a borrowed reference instead of resolving it.
    return Envelope("object_store", pid, node, body=[ray.put(box(payload))], nbytes=nbytes)


def unpack(envelope: Envelope) -> Any:
    if envelope.path == "local":
        if envelope.producer_pid != os.getpid():
            raise RuntimeError("a same-process channel item reached another process (routing bug)")
        with _local_lock:
            return _local_items.pop(envelope.local_id)
    if envelope.path == "inline":
        return envelope.body
    if envelope.path == "object_store":
        return unbox(ray.get(envelope.body[0]))
    if envelope.path == "cuda_ipc":
        return unbox(envelope.body)
    if envelope.path == "p2p":
        from infinirl.runtime import p2p

        return p2p.take(envelope.body)
    raise ValueError(f"unknown transport path {envelope.path!r}")


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
    """Inverse of ``box`` (and of ``walk``'s container boxes); ``leaf`` maps custom placeholders."""
    if isinstance(payload, _TensorBox):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # shared-memory arrays are flagged read-only
            tensor = torch.from_numpy(payload.array)
        dtype = _DTYPE_BY_NAME[payload.dtype]
        return tensor.view(dtype) if tensor.dtype != dtype else tensor
    if isinstance(payload, _CudaBox):
        return payload.rebuild(*payload.args)
    if leaf is not None and isinstance(payload, _Placeholder):
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


@dataclass
class _Placeholder:
    """Stands for the ``index``-th tensor of a payload whose data travels separately (p2p)."""

    index: int


def _is_tensordict(obj: Any) -> bool:
    return type(obj).__name__ == "TensorDict" and hasattr(obj, "batch_size")
