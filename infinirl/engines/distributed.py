"""Where a training process computes: its process group, its device and its compute dtype.

:func:`init_distributed` joins the default group from ``RANK/WORLD_SIZE/MASTER_ADDR/MASTER_PORT``
(gloo for CPU engines; ``cuda:nccl,cpu:gloo`` for GPU engines), or, without those variables, makes
a one-rank group in-process. Nothing here destroys a group: the worker that owns the process does.
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist

from infinirl.engines.cpu_dtype import resolve_cpu_dtype

__all__ = ["barrier", "check_backend", "compute_dtype", "init_distributed", "resolve_device_type", "select_device"]


def init_distributed(device_type: str = "cpu") -> bool:
    """Make sure the default process group exists; return True if this call created it.

    With ``MASTER_ADDR`` set (a launched worker) it joins via ``env://`` using ``RANK`` and
    ``WORLD_SIZE``; otherwise it creates a one-rank group on an in-memory store, so a plain script
    or test needs no setup. ``device_type`` picks the backend: gloo for CPU engines, and
    ``cuda:nccl,cpu:gloo`` for CUDA engines (NCCL for tensors on GPU, gloo for CPU-side objects).
    An existing group is checked against ``device_type``, since the wrong backend would only fail
    later, deep inside FSDP.
    """
    if dist.is_initialized():
        check_backend(device_type)
        return False
    backend = "cuda:nccl,cpu:gloo" if device_type == "cuda" else "gloo"
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if "MASTER_ADDR" in os.environ:
        dist.init_process_group(backend, rank=int(os.environ.get("RANK", "0")), world_size=world_size)
    elif world_size == 1:
        dist.init_process_group(backend, store=dist.HashStore(), rank=0, world_size=1)
    else:
        raise RuntimeError(
            f"init_distributed: WORLD_SIZE={world_size} but MASTER_ADDR/MASTER_PORT are not set; "
            "the launcher must export them so ranks can meet."
        )
    return True


def check_backend(device_type: str) -> None:
    """Refuse a default group whose backend cannot carry ``device_type`` tensors."""
    backend = str(dist.get_backend())
    needed = "nccl" if device_type == "cuda" else "gloo"
    if needed not in backend:
        raise RuntimeError(
            f"the default process group uses backend {backend!r}, but a {device_type} engine needs "
            f"{needed} (init with 'cuda:nccl,cpu:gloo' on GPU, 'gloo' on CPU, or let "
            "init_distributed() create the group)"
        )


def resolve_device_type(choice: str) -> str:
    """``TrainEngineConfig.device`` (``auto``/``cpu``/``cuda``) -> ``"cpu"`` or ``"cuda"``."""
    if choice == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("TrainEngineConfig.device='cuda' but CUDA is not available")
    if choice == "cpu" or (choice == "auto" and not torch.cuda.is_available()):
        return "cpu"
    return "cuda"


def select_device(device_type: str) -> torch.device:
    """This rank's device (a CUDA rank also makes it the current device)."""
    if device_type == "cpu":
        return torch.device("cpu")
    # A Ray worker usually sees exactly one GPU; torchrun-style launches see all and use LOCAL_RANK.
    local_rank = int(os.environ.get("LOCAL_RANK", dist.get_rank() % torch.cuda.device_count()))
    torch.cuda.set_device(local_rank)
    return torch.device("cuda", local_rank)


def compute_dtype(choice: str, device: torch.device) -> torch.dtype:
    """``TrainEngineConfig.param_dtype`` on ``device`` -> the forward/backward dtype."""
    if choice == "float32":
        return torch.float32
    if choice == "bfloat16":
        if device.type == "cpu":
            return getattr(torch, resolve_cpu_dtype("bfloat16"))  # float32 on CPUs without native bf16
        return torch.bfloat16
    if device.type == "cuda" and torch.cuda.is_bf16_supported():
        return torch.bfloat16
    return torch.float32


def barrier(device: torch.device) -> None:
    """A barrier of the default group; on CUDA pinned to ``device`` (NCCL would otherwise guess)."""
    if device.type == "cuda":
        dist.barrier(device_ids=[device.index])
    else:
        dist.barrier()
