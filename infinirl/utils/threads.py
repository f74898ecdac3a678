"""How many CPU threads a worker process computes with."""

from __future__ import annotations

import os

__all__ = ["limit_threads"]


def limit_threads(num_threads: int) -> None:
    """Cap this process's torch/OpenMP threads at ``num_threads`` (0 leaves the defaults).

    Several workers share a host's cores; each one spreading its small kernels over every core
    would make them preempt each other. ``OMP_NUM_THREADS`` is set too (if unset) for libraries
    that read it when they first start a thread team."""
    if not num_threads:
        return
    os.environ.setdefault("OMP_NUM_THREADS", str(num_threads))
    try:
        import torch
    except ImportError:  # an env-only process may run without torch
        return
    torch.set_num_threads(num_threads)
