"""Moving payloads between processes by the cheapest path, with only metadata through queues.

``pack(payload)`` returns an ``Envelope``, small and cheap to send through a channel's queue;
``unpack(envelope)`` returns the payload in the consumer. The path is chosen per payload:

- **inline**: small payloads (< ``INLINE_LIMIT_BYTES`` of tensor data) ride inside the envelope, as
  Ray itself inlines small task arguments: one RPC, no object-store round trip.
- **local**: producer and consumer are the same process: the object is handed over by reference.
- **object store**: CPU tensors are flattened to numpy views and ``ray.put`` once; a consumer on
  the same node maps them from shared memory with zero copies, another node pulls them directly
  from the producer's node. (Ray pickles a ``torch.Tensor`` by copying its data, while a numpy
  view goes out-of-band and is mapped without a copy: that is why tensors are boxed here.)
- **cuda_ipc**: CUDA tensors travel as CUDA IPC handles when the consumer sees the same GPU; the
  producer keeps them alive until the consumer has rebuilt them.
- **p2p**: tensors go producer -> consumer over a pairwise process group (see ``p2p``).

Payloads may be tensors, dicts/lists/tuples/dataclasses/TensorDicts of tensors, or any picklable
object (see ``payload``). Delivered tensors are zero-copy views: each channel item reaches exactly
one consumer, so that consumer may modify them in place.
"""

from __future__ import annotations

import itertools
import os
import threading
from dataclasses import dataclass
from typing import Any

import ray

from infinirl.runtime import p2p
from infinirl.runtime.payload import box, tensor_bytes, tensors_in, unbox

INLINE_LIMIT_BYTES = 64 * 1024

_local_items: dict[int, Any] = {}
_local_lock = threading.Lock()
_ids = itertools.count()


@dataclass
class Envelope:
    """What a channel queue holds: the path taken, the producer, and a ref or the inline payload."""

    path: str
    producer_pid: int
    producer_node: str
    body: Any = None
    local_id: int | None = None
    nbytes: int = 0


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
        return p2p.take(envelope.body)
    raise ValueError(f"unknown transport path {envelope.path!r}")


def unpack_many(envelopes: list[Envelope]) -> list[Any]:
    """``unpack`` of several envelopes, fetching every object-store payload in one ``ray.get``
    (one round trip to the object store instead of one per item)."""
    refs = [e.body[0] for e in envelopes if e.path == "object_store"]
    fetched = iter(ray.get(refs)) if len(refs) > 1 else None
    return [unbox(next(fetched)) if fetched is not None and e.path == "object_store" else unpack(e)
            for e in envelopes]
