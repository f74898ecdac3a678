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

__all__ = ["check_dtype_name", "cpu_bf16_is_fast", "resolve_cpu_dtype", "resolve_dtype", "resolve_weights_dtype"]

_BF16_NAMES = ("bfloat16", "bf16")
_DTYPE_ALIASES = {
    "float32": torch.float32, "fp32": torch.float32, "float": torch.float32,
    "bfloat16": torch.bfloat16, "bf16": torch.bfloat16,
    "float16": torch.float16, "fp16": torch.float16, "half": torch.float16,
}


def resolve_dtype(dtype: torch.dtype | str) -> torch.dtype:
    """Accept ``torch.bfloat16`` or config-friendly strings like ``"bf16"`` / ``"float32"``."""
    if isinstance(dtype, torch.dtype):
        return dtype
    try:
        return _DTYPE_ALIASES[str(dtype).lower()]
    except KeyError:
        raise ValueError(
            f"unknown dtype {dtype!r}; use one of {sorted(_DTYPE_ALIASES)} or a torch.dtype"
        ) from None


def check_dtype_name(name: str, key: str) -> None:
    """ConfigError naming ``key`` unless :func:`resolve_dtype` takes ``name``: a misspelt dtype is
    refused when the config loads, not by a worker that builds its engine with it."""
    import difflib

    from infinirl.config import ConfigError

    if str(name).lower() in _DTYPE_ALIASES:
        return
    near = difflib.get_close_matches(str(name).lower(), list(_DTYPE_ALIASES), n=1)
    hint = f" Did you mean '{near[0]}'?" if near else ""
    raise ConfigError(f"{key}={name!r} is not a dtype.{hint} Choose one of: {', '.join(sorted(_DTYPE_ALIASES))}")


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
    try:
        dtype = resolve_dtype(name)
    except ValueError as error:
        raise ValueError(f"policy.kwargs.dtype: {error}") from None
    if dtype is torch.bfloat16 and not torch.cuda.is_available():
        return resolve_dtype(resolve_cpu_dtype("bfloat16"))
    return dtype


@functools.cache
def _warn_once() -> None:
    warnings.warn("bfloat16 was requested on a CPU without native bf16 arithmetic (no AVX512-BF16/AMX): "
                  "bf16 matrix products run many times slower than float32 here, so float32 is used instead. "
                  "Set INFINIRL_CPU_BF16=1 to keep bfloat16.", stacklevel=3)
