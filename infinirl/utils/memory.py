"""Peak memory of this process: what a user sizes a machine by, logged by the trainers."""

from __future__ import annotations

import resource

import torch

__all__ = ["peak_memory_bytes"]


def peak_memory_bytes(device: torch.device | str = "cpu") -> float:
    """The GPU allocator's peak on a CUDA ``device``; else the process's peak resident set (Linux
    reports it in kilobytes)."""
    device = torch.device(device)
    if device.type == "cuda":
        return float(torch.cuda.max_memory_allocated(device))
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024
