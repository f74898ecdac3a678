"""Point-to-point tensor transfer between two worker processes: NCCL across GPUs, gloo on CPU.

Used when a payload cannot take a cheaper path: CUDA tensors whose consumer is on another GPU
(CUDA IPC needs the same device) or another node, or channels created with ``transport="p2p"``.

Pull protocol. ``offer(payload)`` keeps the producer's tensors alive in a process-local outbox
and returns a small description (placeholders + shapes). The consumer that takes the item calls
the producer's host (``_infinirl_p2p_serve``, served on a dedicated thread, so it runs while the
producer's own method keeps working) and both sides join a *pairwise* process group, created once
per (producer, consumer, backend) through a TCPStore the consumer hosts. The producer sends each
tensor, the consumer receives into fresh buffers on its device. Nothing passes through a third
process.
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
_lock = threading.Lock()
_ids = itertools.count()
_comm = ThreadPoolExecutor(max_workers=1, thread_name_prefix="infinirl-p2p")
TIMEOUT = datetime.timedelta(seconds=300)
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
    addr, port, store = ray.util.get_node_ip_address(), 0, None
    if key not in _groups:
        with socket.socket() as sock:
            sock.bind(("", 0))
            port = sock.getsockname()[1]
        import torch.distributed as dist

        store = dist.TCPStore(addr, port, 2, is_master=True, timeout=TIMEOUT, wait_for_workers=False)
    serving = body.host._infinirl_p2p_serve.remote(body.item, key, addr, port, backend)
    buffers = [torch.empty(shape, dtype=DTYPE_BY_NAME[dtype], device=device)
               for shape, dtype in zip(body.shapes, body.dtypes)]

    def receive() -> None:
        group = _groups.get(key) or _join(key, store, rank=1, backend=backend)
        for buffer in buffers:
            group.recv([buffer], 0, 0).wait()

    # The join and the receives wait for the producer for up to TIMEOUT; watched from here, a
    # producer that died or failed to serve ends the pull at once with its own error.
    receiving = concurrent.futures.Future()
    threading.Thread(target=_run_into, args=(receiving, receive), name="infinirl-p2p-pull", daemon=True).start()
    while True:
        try:
            receiving.result(timeout=WATCH_S)
            break
        except concurrent.futures.TimeoutError:
            finished, _ = ray.wait([serving], timeout=0)
            if finished:
                _raise_if_serving_failed(serving, key, body)
        except Exception:  # the pair's connection broke (an existing group whose producer died)
            _groups.pop(key, None)
            finished, _ = ray.wait([serving], timeout=WATCH_S * 10)
            if finished:
                _raise_if_serving_failed(serving, key, body)
            raise
    ray.get(serving)  # surfaces a producer-side failure
    return buffers


def _run_into(future: concurrent.futures.Future, fn) -> None:
    try:
        fn()
    except BaseException as exc:
        future.set_exception(exc)
    else:
        future.set_result(None)


def _raise_if_serving_failed(serving, key: tuple, body: Offer) -> None:
    """The producer answered the pull while this side still waits: if it failed, the pair's group
    is left with a receive nobody will match (forgotten, so the next pull makes a new one) and the
    producer's error is raised."""
    try:
        ray.get(serving)
    except Exception as exc:
        _groups.pop(key, None)
        from infinirl.runtime.errors import ChannelError

        raise ChannelError(f"p2p item {body.item} from process {body.producer_pid}: the producer could not send it "
                           f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from exc


def _join(key: tuple, store, rank: int, backend: str):
    import torch.distributed as dist

    if backend == "nccl":
        from torch.distributed import ProcessGroupNCCL

        group = ProcessGroupNCCL(dist.PrefixStore("p2p", store), rank, 2)
    else:
        group = dist.ProcessGroupGloo(dist.PrefixStore("p2p", store), rank, 2, TIMEOUT)
    _groups[key] = group
    return group


async def serve_async(item: int, key: tuple, addr: str, port: int, backend: str) -> int:
    """Producer side, from the host's event loop: ``serve`` on the p2p thread (the worker's own
    method keeps the compute thread meanwhile)."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(_comm, serve, item, key, addr, port, backend)


def serve(item: int, key: tuple, addr: str, port: int, backend: str) -> int:
    """Producer side (on the p2p thread): send the item's tensors to the consumer, then forget them."""
    import torch.distributed as dist

    with _lock:
        tensors = _outbox.pop(item)
    group = _groups.get(key)
    if group is None:
        store = dist.TCPStore(addr, port, 2, is_master=False, timeout=TIMEOUT)
        group = _join(key, store, rank=0, backend=backend)
    sent = 0
    for tensor in tensors:
        group.send([tensor], 1, 0).wait()
        sent += tensor.numel() * tensor.element_size()
    return sent


def release(item: int) -> None:
    with _lock:
        _outbox.pop(item, None)
