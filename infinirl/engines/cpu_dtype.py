"""bfloat16 on CPUs without native bf16 arithmetic falls back to float32.

Why: PyTorch runs bf16 matrix products fast on x86 CPUs with AVX512-BF16 or AMX, but on the many
that have only AVX2 (AMD Zen 2/3, older Intel) it takes a slow path, many times slower than float32,
which turns a training step of minutes into one of tens of minutes. On such a CPU a requested
``bfloat16`` becomes ``float32`` (with one warning), for the trainer's compute dtype and the
rollout's weights alike, and for a VLA policy's weights on a CPU-only host. ``INFINIRL_CPU_BF16=1``
keeps bf16 anyway. Other architectures (Arm) keep what was asked: we do not guess there.
"""

from __future__ import annotations

import functools
import os
import platform
import warnings

import torch

__all__ = ["cpu_bf16_is_fast", "resolve_cpu_dtype", "resolve_weights_dtype"]

_BF16_NAMES = ("bfloat16", "bf16")
_WEIGHT_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "bf16": torch.bfloat16,
                  "float16": torch.float16}


@functools.cache
def cpu_bf16_is_fast() -> bool:
    """Whether this CPU computes bf16 natively (x86: AVX512-BF16 or AMX); True off x86."""
    if os.environ.get("INFINIRL_CPU_BF16") == "1":
        return True
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return True
    amx = getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    return bool(torch.cpu._is_avx512_bf16_supported() or amx())


def resolve_cpu_dtype(name: str) -> str:
    """``name`` unchanged, except ``"bfloat16"`` on a CPU without native bf16: ``"float32"``."""
    if name in _BF16_NAMES and not cpu_bf16_is_fast():
        _warn_once()
        return "float32"
    return name


def resolve_weights_dtype(name: str) -> torch.dtype:
    """The dtype a policy's weights load in: ``name``, except bf16 on a CPU-only host without native bf16.

    For models built before they know their device (a VLA policy loads its checkpoint, then its
    worker moves it): with a CUDA device visible the weights will compute there, so bf16 is kept.
    """
    if name not in _WEIGHT_DTYPES:
        raise ValueError(f"dtype {name!r} is not one of {sorted(_WEIGHT_DTYPES)}: set policy.kwargs.dtype to one")
    resolved = name if torch.cuda.is_available() else resolve_cpu_dtype(name)
    return _WEIGHT_DTYPES[resolved]


@functools.cache
def _warn_once() -> None:
    warnings.warn("bfloat16 was requested on a CPU without native bf16 arithmetic (no AVX512-BF16/AMX): "
                  "bf16 matrix products run many times slower than float32 here, so float32 is used instead. "
                  "Set INFINIRL_CPU_BF16=1 to keep bfloat16.", stacklevel=3)
