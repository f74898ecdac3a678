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

from infinirl.utils.atomic import atomic_open

__all__ = ["write_mp4"]

FFMPEG_HINT = "pip install imageio-ffmpeg (it comes with `pip install 'infinirl[sim]'`)"


def write_mp4(path: str, frames: Sequence[np.ndarray], fps: int = 30) -> str:
    """Encode ``frames`` (``[H, W, 3]`` uint8 each) as an H.264 mp4 at ``path``; returns ``path``."""
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        raise RuntimeError(f"writing the eval video {path} needs imageio's ffmpeg writer: {FFMPEG_HINT}")
    if not len(frames):
        raise ValueError(f"no frames to write to {path}")
    import imageio.v3 as iio

    with atomic_open(path, "wb", suffix=".tmp.mp4") as handle:
        # imageio encodes into a file of its own and copies it into the open handle: the handle of
        # a temporary file has no path to give the ffmpeg writer, and the extension must be named.
        iio.imwrite(handle, np.stack(frames), extension=".mp4", plugin="FFMPEG", fps=fps, macro_block_size=1)
    return path
