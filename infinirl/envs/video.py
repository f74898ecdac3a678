"""Writing evaluation videos: one mp4 writer for every runner, atomic and with a clear error.

Why a helper: imageio picks its writer from what is installed. Without ``imageio-ffmpeg`` it hands
an ``.mp4`` path to another plugin (tifffile, for one), which fails with an unrelated message
("unexpected keyword argument 'fps'") after creating a stub file. We check for the ffmpeg writer
first, name the package to install, and write to a temporary file that is renamed into place, so
a video either exists whole or not at all.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence

import numpy as np

from infinirl.utils.atomic import atomic_path

__all__ = ["write_mp4"]

FFMPEG_HINT = "pip install imageio-ffmpeg (it comes with `pip install 'infinirl[sim]'`)"


def write_mp4(path: str, frames: Sequence[np.ndarray], fps: int = 30) -> str:
    """Encode ``frames`` (``[H, W, 3]`` uint8 each) as an H.264 mp4 at ``path``; returns ``path``."""
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        raise RuntimeError(f"writing the eval video {path} needs imageio's ffmpeg writer: {FFMPEG_HINT}")
    if not len(frames):
        raise ValueError(f"no frames to write to {path}")
    import imageio.v2 as imageio

    with atomic_path(path, suffix=".tmp.mp4") as tmp:  # the extension selects the ffmpeg writer
        imageio.mimsave(tmp, list(frames), fps=fps, macro_block_size=1, format="FFMPEG")
    return path
