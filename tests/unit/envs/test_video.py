"""Eval videos: a whole mp4 or none, and a missing ffmpeg writer named with the fix."""

import importlib.util

import numpy as np
import pytest

from infinirl.envs import video
from infinirl.envs.video import write_mp4

pytest.importorskip("imageio_ffmpeg")


def frames(n=6, size=16):
    return [np.full((size, size, 3), 30 * i, dtype=np.uint8) for i in range(n)]


def test_writes_a_readable_mp4_and_leaves_no_temporary(tmp_path):
    import imageio.v2 as imageio

    path = write_mp4(str(tmp_path / "runs" / "eval.mp4"), frames(), fps=10)
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["eval.mp4"]
    decoded = imageio.mimread(path)
    assert len(decoded) == 6 and decoded[0].shape == (16, 16, 3)


def test_without_ffmpeg_it_names_the_package_and_writes_nothing(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(video.importlib.util, "find_spec",
                        lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    with pytest.raises(RuntimeError, match="pip install imageio-ffmpeg"):
        write_mp4(str(tmp_path / "eval.mp4"), frames())
    assert list(tmp_path.iterdir()) == []


def test_a_failed_encode_leaves_neither_the_video_nor_a_stub(tmp_path, monkeypatch):
    import imageio.v2 as imageio

    def fail(path, *args, **kwargs):
        with open(path, "wb") as handle:  # the encoder got as far as a stub before the disk filled
            handle.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(imageio, "mimsave", fail)
    with pytest.raises(OSError, match="disk full"):
        write_mp4(str(tmp_path / "eval.mp4"), frames())
    assert list(tmp_path.iterdir()) == []
