"""Point-to-point tensor transfer between two worker processes: NCCL across GPUs, gloo on CPU.

Used when a payload cannot take a cheaper path: CUDA tensors whose consumer is on another GPU
(CUDA IPC needs the same device) or another node, or channels created with ``transport="p2p"``.

Pull protocol. ``offer(payload)`` keeps the producer's tensors alive in a process-local outbox
and returns a small description (placeholders + shapes). The consumer that takes the item calls
the producer's host (``_infinirl_p2p_serve``, served on a dedicated thread, so it runs while the
producer's own method keeps working) and both sides join a *pairwise* process group, created once
per (producer, consumer, backend) through a TCPStore the consumer hosts. The producer sends the
item's id, then each tensor; the consumer checks the id and receives into fresh buffers on its
device. Nothing passes through a third process.

A failed pull (either side) makes both sides give the pair's group up: the consumer's next pull
sends a fresh rendezvous port, on which the producer always builds a new group, and the producer
dropping the old one ends a receive the failed pull left pending on it, so that receive can never
take a later item. Pulls from one producer into one process take turns.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import datetime
import itertools
import os
import socket
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import ray
import torch

from infinirl.runtime import processes
from infinirl.runtime.payload import DTYPE_BY_NAME, Placeholder, tensors_in, unbox, walk

_outbox: dict[int, list[torch.Tensor]] = {}
_groups: dict[tuple, Any] = {}
_pair_locks: dict[tuple, threading.Lock] = {}
_lock = threading.Lock()
_ids = itertools.count()
_comm = ThreadPoolExecutor(max_workers=1, thread_name_prefix="infinirl-p2p")
TIMEOUT = datetime.timedelta(seconds=300)
PULLS = ThreadPoolExecutor(max_workers=4, thread_name_prefix="infinirl-p2p-take")
"""Where asynchronous getters unpack items: a pull blocks until its producer has sent the item, and
on an actor's event loop it would keep that loop from serving pulls of its own (two ranks each
pulling from the other would wait on each other until TIMEOUT)."""
WATCH_S = 0.5
"""How often a consumer's pull checks that its producer is still serving it."""


def available() -> bool:
    """P2P needs a producer that can serve pulls: a Worker process (not the driver)."""
    return processes.host_handle() is not None


@dataclass
class Offer:
    host: Any
    item: int
    producer_pid: int
    skeleton: Any
    shapes: list[tuple[int, ...]]
    dtypes: list[str]
    device: str
    gpu_uuid: str | None = None
    ipc: Any = None


def offer(payload: Any, with_ipc: bool = False) -> Offer:
    tensors = [t.detach().contiguous() for t in tensors_in(payload)]
    devices = {t.device.type for t in tensors}
    if len(devices) > 1:
        raise ValueError("a p2p payload must keep all its tensors on one device type")
    counter = itertools.count()
    skeleton = walk(payload, lambda t: Placeholder(next(counter)))
    item = next(_ids)
    with _lock:
        _outbox[item] = tensors
    device = devices.pop() if devices else "cpu"
    uuid = str(torch.cuda.get_device_properties(tensors[0].device).uuid) if device == "cuda" else None
    ipc = None
    if with_ipc and device == "cuda":
        from torch.multiprocessing.reductions import reduce_tensor

        ipc = [reduce_tensor(t) for t in tensors]
    return Offer(processes.host_handle(), item, os.getpid(), skeleton, [tuple(t.shape) for t in tensors],
                 [str(t.dtype) for t in tensors], device, uuid, ipc)


def _visible_gpu_uuids() -> set[str]:
    if not torch.cuda.is_available():
        return set()
    return {str(torch.cuda.get_device_properties(i).uuid) for i in range(torch.cuda.device_count())}


def take(body: Offer) -> Any:
    """Consumer side: rebuild the payload (CUDA IPC when we see the producer's GPU, else pull)."""
    if body.ipc is not None and body.gpu_uuid in _visible_gpu_uuids():
        tensors = [rebuild(*args) for rebuild, args in body.ipc]
        body.host._infinirl_p2p_release.remote(body.item)
    else:
        tensors = _pull(body)
    return unbox(body.skeleton, leaf=lambda placeholder: tensors[placeholder.index])


def _pull(body: Offer) -> list[torch.Tensor]:
    backend = "nccl" if body.device == "cuda" else "gloo"
    device = "cuda" if backend == "nccl" else "cpu"
    key = (body.producer_pid, os.getpid(), backend)
    with _pair_lock(key):  # pulls from one producer take turns on the pair's group
        return _pull_over_pair(body, key, backend, device)


def _pull_over_pair(body: Offer, key: tuple, backend: str, device: str) -> list[torch.Tensor]:
    addr, port, store = ray.util.get_node_ip_address(), 0, None
    group = _groups.get(key)
    if group is None:
        with socket.socket() as sock:
            sock.bind(("", 0))
            port = sock.getsockname()[1]
        import torch.distributed as dist

        store = dist.TCPStore(addr, port, 2, is_master=True, timeout=TIMEOUT, wait_for_workers=False)
    serving = body.host._infinirl_p2p_serve.remote(body.item, key, addr, port, backend)
    header = torch.empty(1, dtype=torch.int64, device=device)
    buffers = [torch.empty(shape, dtype=DTYPE_BY_NAME[dtype], device=device)
               for shape, dtype in zip(body.shapes, body.dtypes)]
    joined = [group]

    def receive() -> None:
        # The group this pull was started with, never a later one: a receive left behind by a
        # failed pull must not catch the next item (the producer drops that group, which ends it).
        if joined[0] is None:
            joined[0] = _join(store, rank=1, backend=backend)
        joined[0].recv([header], 0, 0).wait()
        if int(header.item()) != body.item:
            raise _channel_error(f"p2p pull of item {body.item} from process {body.producer_pid} received item "
                                 f"{int(header.item())}: the pair's transfers crossed")
        for buffer in buffers:
            joined[0].recv([buffer], 0, 0).wait()

    # The join and the receives wait for the producer for up to TIMEOUT; watched from here, a
    # producer that died or failed to serve ends the pull at once with its own error.
    receiving = concurrent.futures.Future()
    threading.Thread(target=_run_into, args=(receiving, receive), name="infinirl-p2p-pull", daemon=True).start()
    try:
        while True:
            try:
                receiving.result(timeout=WATCH_S)
                break
            except concurrent.futures.TimeoutError:
                finished, _ = ray.wait([serving], timeout=0)
                if finished:
                    _raise_if_serving_failed(serving, body)
            except Exception:  # the pair's connection broke (an existing group whose producer died)
                finished, _ = ray.wait([serving], timeout=WATCH_S * 10)
                if finished:
                    _raise_if_serving_failed(serving, body)
                raise
        ray.get(serving)  # surfaces a producer-side failure
    except BaseException:
        # Both sides give the pair's group up after any failure: the next pull rendezvous afresh,
        # and the producer, seeing a new port, replaces its own.
        _groups.pop(key, None)
        _abandon(joined[0], backend)
        raise
    _groups[key] = joined[0]
    return buffers


def _pair_lock(key: tuple) -> threading.Lock:
    with _lock:
        return _pair_locks.setdefault(key, threading.Lock())


def _abandon(group, backend: str) -> None:
    """A group whose receive may still be pending: NCCL's abort ends it (it would hold the device's
    stream); a gloo receive ends when the producer drops its side of the group."""
    if group is not None and backend == "nccl" and hasattr(group, "abort"):
        group.abort()


def _channel_error(message: str) -> Exception:
    from infinirl.runtime.errors import ChannelError

    return ChannelError(message)


def _run_into(future: concurrent.futures.Future, fn) -> None:
    try:
        fn()
    except BaseException as exc:
        future.set_exception(exc)
    else:
        future.set_result(None)


def _raise_if_serving_failed(serving, body: Offer) -> None:
    """The producer answered the pull while this side still waits: if it failed, its error is raised
    (the caller then gives the pair's group up)."""
    try:
        ray.get(serving)
    except Exception as exc:
        raise _channel_error(f"p2p item {body.item} from process {body.producer_pid}: the producer could not send "
                             f"it ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from exc


def _join(store, rank: int, backend: str):
    import torch.distributed as dist

    if backend == "nccl":
        from torch.distributed import ProcessGroupNCCL

        return ProcessGroupNCCL(dist.PrefixStore("p2p", store), rank, 2, nccl_options(TIMEOUT))
    return dist.ProcessGroupGloo(dist.PrefixStore("p2p", store), rank, 2, TIMEOUT)


def nccl_options(timeout: datetime.timedelta):
    """Options of a ``ProcessGroupNCCL`` whose collectives give up after ``timeout`` (by default
    NCCL's own, which is unrelated to the store's)."""
    from torch.distributed import ProcessGroupNCCL

    options = ProcessGroupNCCL.Options()
    options._timeout = timeout
    return options


async def serve_async(item: int, key: tuple, addr: str, port: int, backend: str) -> int:
    """Producer side, from the host's event loop: ``serve`` on the p2p thread (the worker's own
    method keeps the compute thread meanwhile)."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(_comm, serve, item, key, addr, port, backend)


def serve(item: int, key: tuple, addr: str, port: int, backend: str) -> int:
    """Producer side (on the p2p thread): send the item's id, then its tensors, to the consumer,
    and forget them. ``port`` 0: over the pair's group; else the consumer made a new rendezvous
    (its first pull, or its first since one failed): a group kept from before is stale."""
    import torch.distributed as dist

    with _lock:
        tensors = _outbox.pop(item, None)
    try:
        if tensors is None:
            raise _channel_error(f"p2p item {item} is no longer held by process {os.getpid()} (released before "
                                 f"its consumer pulled it)")
        if port:
            _groups.pop(key, None)  # dropping the stale group ends a receive its consumer left pending on it
            store = dist.TCPStore(addr, port, 2, is_master=False, timeout=TIMEOUT)
            _groups[key] = _join(store, rank=0, backend=backend)
        group = _groups.get(key)
        if group is None:
            raise _channel_error(f"process {os.getpid()} holds no p2p group with process {key[1]}, which asked "
                                 f"to use one; its next pull makes a new one")
        device = tensors[0].device if tensors else "cpu"
        group.send([torch.tensor([item], dtype=torch.int64, device=device)], 1, 0).wait()
        sent = 0
        for tensor in tensors:
            group.send([tensor], 1, 0).wait()
            sent += tensor.numel() * tensor.element_size()
    except BaseException:
        # The consumer gives it up too, and the next pull rendezvous afresh. No reference may
        # outlive this (the traceback keeps this frame): dropping the group ends the consumer's
        # receive left pending on it.
        _groups.pop(key, None)
        group = None  # noqa: F841
        raise
    return sent


def release(item: int) -> None:
    with _lock:
        _outbox.pop(item, None)
