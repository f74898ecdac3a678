"""Where InfiniRL keeps what it builds once and reuses (converted models, simulator configs)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_root"]


def cache_root() -> Path:
    """Root of InfiniRL's on-disk cache: ``$INFINIRL_CACHE`` or ``~/.cache/infinirl``."""
    return Path(os.environ.get("INFINIRL_CACHE", Path.home() / ".cache" / "infinirl")).expanduser()
