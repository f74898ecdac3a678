"""How many CPU threads a worker process computes with."""

from __future__ import annotations

import os

__all__ = ["limit_threads", "spin_wait_env"]


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


def spin_wait_env(num_threads: int) -> dict[str, str]:
    """Environment variables a worker rank's process starts with when it computes with
    ``num_threads`` torch threads (0: torch's default, every core).

    Every worker waits passively in OpenMP (``OMP_WAIT_POLICY=PASSIVE``, see runtime.cluster): a
    thread that finishes a parallel region sleeps at once, so idle processes give the cores back.
    A rank with several threads that runs many small kernels back to back (a PPO update, a VLA's
    denoising steps) would then wake a sleeping helper thread for each one, which costs more than
    the kernel: let its threads spin ~3 ms first (``GOMP_SPINCOUNT``, libgomp's own default when no
    policy is set), then sleep. Read once, when torch loads OpenMP: hence set from the process's
    start. ``python benchmarks/omp_wait.py`` measures it on the VLA demo's acting."""
    return {} if num_threads == 1 else {"GOMP_SPINCOUNT": "300000"}
