"""Moving payloads between processes by the cheapest path, with only metadata through queues.

``pack(payload)`` returns an ``Envelope``, small and cheap to send through a channel's queue;
``unpack(envelope)`` returns the payload in the consumer. The path is chosen per payload:

- **inline**: small payloads (< ``INLINE_LIMIT_BYTES`` of array data: torch tensors, numpy arrays
  and bytes objects, nested in containers or not) ride inside the envelope, as
  Ray itself inlines small task arguments: one RPC, no object-store round trip.
- **local**: producer and consumer are the same process: the object is handed over by reference.
- **shm**: every consumer of the channel is on the producer's node: CPU tensors are copied into a
  segment of the producer's shared-memory pool, which is reused once the consumer has dropped the
  tensors; the consumer maps it (once per segment) and receives views of it (see ``shm_pool``).
  The channel serves such an item only to a getter on the producer's node.
- **object store**: CPU tensors are flattened to numpy views and ``ray.put`` once; a consumer on
  the same node maps them from shared memory with zero copies, another node pulls them directly
  from the producer's node. (Ray pickles a ``torch.Tensor`` by copying its data, while a numpy
  view goes out-of-band and is mapped without a copy: that is why tensors are boxed here.) Taken
  when a consumer may be on another node, when the shared-memory pool is full, or when the payload
  holds 64 KiB or more of numpy arrays or bytes (shared memory and p2p carry torch tensors only;
  Ray moves numpy arrays out-of-band).
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
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import ray

from infinirl.runtime import p2p, shm_pool
from infinirl.runtime.payload import box, other_array_bytes, tensor_bytes, tensors_in, unbox

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


def shared_memory_reaches(producer_node: str, consumer_nodes: Iterable[str]) -> bool:
    """Whether an item in the producer's shared memory can reach every consumer: all of them
    (and at least one is known) run on the producer's node."""
    nodes = set(consumer_nodes)
    return bool(nodes) and nodes == {producer_node}


def pack(payload: Any, same_process: bool = False, force_p2p: bool = False,
         shared_memory: bool | Callable[[], bool] = False) -> Envelope:
    """Wrap ``payload`` for a queue. ``same_process``: every consumer is this process.
    ``force_p2p``: send tensors point-to-point (a channel created with ``transport="p2p"``).
    ``shared_memory``: every consumer is on this node (see ``shared_memory_reaches``), or a
    function that tells it, asked only for a payload that would otherwise go to the object store."""
    pid, node = os.getpid(), _node_id()
    if same_process:
        local_id = next(_ids)
        with _local_lock:
            _local_items[local_id] = payload
        return Envelope("local", pid, node, local_id=local_id)
    nbytes = tensor_bytes(payload)
    # p2p and shared memory carry torch tensors; numpy arrays and bytes ride in the item's
    # structure, through the channel actor: a payload with many of those takes the object store.
    other = other_array_bytes(payload)
    if force_p2p and p2p.available() and nbytes > other and other < INLINE_LIMIT_BYTES:
        return Envelope("p2p", pid, node, body=p2p.offer(payload), nbytes=nbytes)
    if _has_cuda(payload):
        if p2p.available():  # consumer decides: CUDA IPC on our GPU, NCCL from any other
            return Envelope("p2p", pid, node, body=p2p.offer(payload, with_ipc=True), nbytes=nbytes)
        return Envelope("cuda_ipc", pid, node, body=box(payload, cuda_ipc=True), nbytes=nbytes)
    if nbytes < INLINE_LIMIT_BYTES:
        return Envelope("inline", pid, node, body=payload, nbytes=nbytes)
    item = _write_shared(payload, shared_memory) if other < INLINE_LIMIT_BYTES else None
    if item is not None:
        return Envelope("shm", pid, node, body=item, nbytes=nbytes)
    # The ref sits in a list so Ray passes it as a borrowed reference instead of resolving it.
    return Envelope("object_store", pid, node, body=[ray.put(box(payload))], nbytes=nbytes)


def _write_shared(payload: Any, shared_memory: bool | Callable[[], bool]) -> shm_pool.ShmItem | None:
    """``payload`` written into this process's shared-memory pool, if that may and can be done."""
    pool = shm_pool.pool()
    if not pool.cap_bytes or not (shared_memory if isinstance(shared_memory, bool) else shared_memory()):
        return None
    return pool.write(payload)


def unpack(envelope: Envelope) -> Any:
    if envelope.path == "local":
        if envelope.producer_pid != os.getpid():
            raise RuntimeError("a same-process channel item reached another process (routing bug)")
        with _local_lock:
            return _local_items.pop(envelope.local_id)
    if envelope.path == "inline":
        return envelope.body
    if envelope.path == "shm":
        return shm_pool.read(envelope.body)
    if envelope.path == "object_store":
        return unbox(ray.get(envelope.body[0]))
    if envelope.path == "cuda_ipc":
        return unbox(envelope.body)
    if envelope.path == "p2p":
        return p2p.take(envelope.body)
    raise ValueError(f"unknown transport path {envelope.path!r}")


def discard(envelope: Envelope) -> None:
    """Forget an envelope no consumer will ever unpack (its put failed): its shared-memory segment
    goes back to the pool, its same-process item and its p2p tensors are dropped. Other paths need
    nothing."""
    if envelope.path == "shm" and envelope.producer_pid == os.getpid():
        shm_pool.pool().release(envelope.body)
    elif envelope.path == "local":
        with _local_lock:
            _local_items.pop(envelope.local_id, None)
    elif envelope.path == "p2p" and envelope.producer_pid == os.getpid():
        p2p.release(envelope.body.item)  # the outbox would hold its tensors (GPU memory, maybe) forever


def pinned_pid(envelope: Envelope) -> int | None:
    """The process that alone can unpack ``envelope`` (a same-process item), else None."""
    return envelope.producer_pid if envelope.path == "local" else None


def pinned_node(envelope: Envelope) -> str | None:
    """The node whose processes alone can unpack ``envelope`` (an item in shared memory), else None."""
    return envelope.producer_node if envelope.path == "shm" else None
