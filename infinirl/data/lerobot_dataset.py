"""LeRobotDataset v3.0 on disk: a writer and a reader that need neither LeRobot nor pandas.

A dataset is a folder (``codebase_version`` ``"v3.0"``, the layout LeRobot 0.4 reads)::

    meta/info.json                                  fps, features (dtype, shape, names), totals, path templates
    meta/stats.json                                 per-feature min/max/mean/std/count/quantiles, all episodes
    meta/tasks.parquet                              task string (pandas index) -> task_index
    meta/episodes/chunk-000/file-000.parquet        one row per episode: length, tasks, frame range, the data
                                                    and video file of the episode, its time range in that
                                                    video, and its own stats (``stats/<feature>/<stat>``)
    data/chunk-XXX/file-YYY.parquet                 one row per frame: the non-video features, ``timestamp``,
                                                    ``frame_index``, ``episode_index``, ``index``, ``task_index``
    videos/<video key>/chunk-XXX/file-YYY.mp4       the frames of consecutive episodes, one H.264 stream

Episodes are appended to the current data and video files; a file that has grown past
``data_files_size_in_mb`` / ``video_files_size_in_mb`` is closed at an episode boundary and the
next one opened (``chunks_size`` files per chunk folder), as LeRobot's own writer does. An episode's
frames in a video file start at ``from_timestamp`` = (frames of earlier episodes in that file) / fps.

The writer builds everything in a hidden folder beside ``root`` and renames it into place on
:meth:`LeRobotDatasetWriter.finalize`: a dataset exists whole or not at all.

Video: H.264 (libx264), yuv420p, through the ffmpeg binary of ``imageio-ffmpeg``. A keyframe
every ``gop`` frames (2, LeRobot's choice) keeps decoding one frame at a random timestamp cheap.
Each episode is encoded on its own and the episodes of a file are joined without re-encoding
(as LeRobot does), so a file's size is exact at every episode boundary.
Statistics follow LeRobot's ``compute_episode_stats``/``aggregate_stats``, except that episode
quantiles are exact (``numpy.quantile``) where LeRobot estimates them from a histogram.
"""

from __future__ import annotations

import functools
import json
import os
import re
import shutil
import tempfile
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from infinirl.utils.atomic import replace_directory, write_json_atomic

__all__ = [
    "CODEBASE_VERSION",
    "INDEX_FEATURES",
    "LeRobotDatasetError",
    "LeRobotDatasetReader",
    "LeRobotDatasetWriter",
    "VideoSettings",
    "aggregate_stats",
    "check_ffmpeg",
    "encode_mp4",
    "episode_stats",
    "join_mp4",
    "load_info",
    "read_video_frames",
]

CODEBASE_VERSION = "v3.0"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"

INDEX_FEATURES: dict[str, dict[str, Any]] = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
"""The per-frame bookkeeping columns every LeRobot dataset has; the writer fills them in."""

QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
NUMERIC_DTYPES = ("float32", "float64", "int32", "int64", "bool")
VIDEO_DTYPE = "video"
_MB = 1024 * 1024
_PANDAS_INDEX_COLUMN = "__index_level_0__"  # where pandas keeps an unnamed index in a parquet file
_FFMPEG_TIMEOUT_S = 600  # one episode's video; far above what encoding or joining takes, so only a hang hits it
FFMPEG_HINT = "pip install imageio-ffmpeg (it comes with `pip install 'infinirl[sim]'`)"


class LeRobotDatasetError(ValueError):
    """A dataset that cannot be written or read as asked; the message names the file and the fix."""


@dataclass(frozen=True, kw_only=True)
class VideoSettings:
    """How video features are encoded: libx264 at constant quality ``crf`` (lower = closer to the
    frames, bigger files), a keyframe every ``gop`` frames, x264 ``preset``."""

    crf: int = 18
    gop: int = 2
    preset: str = "medium"

    def __post_init__(self) -> None:
        if not 0 <= self.crf <= 51:
            raise ValueError(f"VideoSettings.crf must be in [0, 51] (x264's range), got {self.crf}")
        if self.gop < 1:
            raise ValueError(f"VideoSettings.gop must be >= 1, got {self.gop}")


# ---------------------------------------------------------------------------------------------
# Statistics


def estimate_num_samples(length: int, min_samples: int = 100, max_samples: int = 10_000, power: float = 0.75) -> int:
    """How many frames of an episode image statistics look at (LeRobot's heuristic)."""
    min_samples = min(min_samples, length)
    return max(min_samples, min(int(length**power), max_samples))


def _array_stats(values: np.ndarray, count: int) -> dict[str, np.ndarray]:
    """Per-column statistics of ``values`` ``[N, D]`` (float64); ``count`` = samples they stand for."""
    stats = {
        "min": values.min(axis=0),
        "max": values.max(axis=0),
        "mean": values.mean(axis=0),
        "std": values.std(axis=0),
        "count": np.array([count], dtype=np.int64),
    }
    quantiles = np.quantile(values, QUANTILES, axis=0)
    for q, value in zip(QUANTILES, quantiles):
        stats[f"q{round(q * 100):02d}"] = value
    return stats


def episode_stats(columns: Mapping[str, np.ndarray], features: Mapping[str, Mapping[str, Any]]) -> dict[str, dict]:
    """LeRobot's per-episode statistics of ``columns`` (feature -> ``[T, *shape]``).

    Vectors: per-dimension stats, shape ``(D,)``; scalar columns ``(1,)``. Videos: per-channel
    stats of pixel values scaled to [0, 1] over evenly spaced frames, shape ``(3, 1, 1)``, with
    ``count`` the number of frames used."""
    out: dict[str, dict] = {}
    for key, data in columns.items():
        if features[key]["dtype"] == VIDEO_DTYPE:
            picks = np.round(np.linspace(0, len(data) - 1, estimate_num_samples(len(data)))).astype(int)
            pixels = data[picks].reshape(-1, data.shape[-1]).astype(np.float64) / 255.0
            stats = _array_stats(pixels, len(picks))
            out[key] = {k: v if k == "count" else v.reshape(-1, 1, 1) for k, v in stats.items()}
        else:
            values = np.asarray(data, dtype=np.float64).reshape(len(data), -1)
            out[key] = _array_stats(values, len(data))
    return out


def aggregate_stats(per_episode: Sequence[Mapping[str, Mapping[str, np.ndarray]]]) -> dict[str, dict]:
    """Whole-dataset statistics from per-episode ones (LeRobot's ``aggregate_stats``): exact min,
    max, mean and std (parallel variance); quantiles are the count-weighted mean of the episodes'."""
    out: dict[str, dict] = {}
    for key in per_episode[0]:
        items = [stats[key] for stats in per_episode]
        counts = np.stack([s["count"] for s in items]).astype(np.float64)
        means = np.stack([s["mean"] for s in items])
        weights = counts.reshape(-1, *([1] * (means.ndim - 1)))
        total = counts.sum()
        mean = (means * weights).sum(axis=0) / total
        variance = ((np.stack([s["std"] for s in items]) ** 2 + (means - mean) ** 2) * weights).sum(axis=0) / total
        merged = {
            "min": np.min(np.stack([s["min"] for s in items]), axis=0),
            "max": np.max(np.stack([s["max"] for s in items]), axis=0),
            "mean": mean,
            "std": np.sqrt(variance),
            "count": np.array([int(total)], dtype=np.int64),
        }
        for name in (k for k in items[0] if k.startswith("q")):
            merged[name] = (np.stack([s[name] for s in items]) * weights).sum(axis=0) / total
        out[key] = merged
    return out


def _stats_to_json(stats: Mapping[str, Mapping[str, np.ndarray]]) -> dict:
    return {key: {name: np.asarray(value).tolist() for name, value in item.items()} for key, item in stats.items()}


# ---------------------------------------------------------------------------------------------
# Video


def _ffmpeg() -> Any:
    try:
        import imageio_ffmpeg
    except ImportError:
        raise LeRobotDatasetError(f"LeRobot datasets store images as mp4 videos: {FFMPEG_HINT}") from None
    return imageio_ffmpeg


def check_ffmpeg() -> None:
    """The ffmpeg binary the videos are encoded and decoded with is there (a LeRobotDatasetError saying
    how to get it otherwise)."""
    try:
        _ffmpeg().get_ffmpeg_exe()
    except RuntimeError as exc:  # imageio-ffmpeg installed without its binary, none on PATH
        raise LeRobotDatasetError(f"{exc}; {FFMPEG_HINT}") from None


def encode_mp4(path: Path, frames: np.ndarray, fps: int, settings: VideoSettings) -> None:
    """Encode ``frames`` ``[T, H, W, 3]`` uint8 as one H.264 (yuv420p) mp4 at ``path``."""
    ffmpeg = _ffmpeg()
    height, width = frames.shape[1:3]
    try:
        stream = ffmpeg.write_frames(
            str(path), (width, height), fps=fps, codec="libx264", pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
            quality=None, macro_block_size=1, ffmpeg_log_level="error", ffmpeg_timeout=_FFMPEG_TIMEOUT_S,
            output_params=["-crf", str(settings.crf), "-g", str(settings.gop), "-preset", settings.preset],
        )
        stream.send(None)  # starts ffmpeg
        for frame in frames:
            stream.send(np.ascontiguousarray(frame))
        stream.close()
    except OSError as exc:
        raise LeRobotDatasetError(f"encoding {path} failed: {' '.join(str(exc).split())[:300]}") from None
    if not path.is_file() or not path.stat().st_size:
        raise LeRobotDatasetError(f"encoding {path} produced no file: ffmpeg stopped early (a full disk?)")


def join_mp4(parts: Sequence[Path], path: Path) -> None:
    """Concatenate mp4 files of one encoding into ``path`` without re-encoding: frame ``k`` of
    part ``j`` keeps its pixels and lands at (frames of parts before ``j`` + ``k``) / fps."""
    import subprocess

    if len(parts) == 1:
        os.replace(parts[0], path)
        return
    listing = path.with_name(path.name + ".parts.txt")
    listing.write_text("".join(f"file '{part.resolve()}'\n" for part in parts))
    command = [_ffmpeg().get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "concat", "-safe", "0",
               "-i", str(listing), "-c", "copy", "-f", "mp4", str(path)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=_FFMPEG_TIMEOUT_S)
    if done.returncode:
        raise LeRobotDatasetError(f"joining {len(parts)} episode videos into {path} failed: "
                                  f"{' '.join(done.stderr.split())[:300]}")
    listing.unlink()
    for part in parts:
        part.unlink()


class _VideoFile:
    """One video file of the dataset while it is being written: each episode is encoded to a part
    of its own (so the file's size is known exactly after every episode, and where the dataset
    rolls over to a new file does not depend on encoder buffering), and the parts are joined,
    without re-encoding, when the file is closed."""

    def __init__(self, path: Path, fps: int, settings: VideoSettings) -> None:
        self.path = path
        self.frames = 0
        self._fps = fps
        self._settings = settings
        self._parts: list[Path] = []
        self._bytes = 0

    def write(self, frames: np.ndarray) -> None:
        part = self.path.with_name(f".{self.path.stem}.part-{len(self._parts):06d}.mp4")
        part.parent.mkdir(parents=True, exist_ok=True)
        encode_mp4(part, frames, self._fps, self._settings)
        self._parts.append(part)
        self._bytes += part.stat().st_size
        self.frames += len(frames)

    def size_mb(self) -> float:
        return self._bytes / _MB

    def close(self) -> None:
        if self._parts:
            join_mp4(self._parts, self.path)
            self._parts = []


def passthrough_params(ffmpeg_version: str) -> list[str]:
    """The output option that keeps every decoded frame with its own timestamp: ``-fps_mode`` since
    FFmpeg 5.1, ``-vsync`` before it (still accepted after, but deprecated), so that an older
    ffmpeg binary (``IMAGEIO_FFMPEG_EXE``, or an older ``imageio-ffmpeg``) reads the videos too."""
    match = re.match(r"\D*(\d+)\.(\d+)", ffmpeg_version)
    if match and (int(match.group(1)), int(match.group(2))) < (5, 1):
        return ["-vsync", "passthrough"]
    return ["-fps_mode", "passthrough"]  # a version string that is not a release number: a recent build


@functools.cache
def _reader_passthrough_params() -> tuple[str, ...]:
    return tuple(passthrough_params(_ffmpeg().get_ffmpeg_version()))


def read_video_frames(path: Path, start_s: float, count: int, fps: int) -> np.ndarray:
    """``count`` consecutive frames ``[count, H, W, 3]`` uint8 of an mp4, the first at time
    ``start_s``; one-line :class:`LeRobotDatasetError` naming the file if it cannot be decoded."""
    ffmpeg = _ffmpeg()
    # Seek half a frame early: ffmpeg outputs the frames at or after the seek time, and a time
    # computed in floating point may land a hair past the wanted frame's timestamp.
    seek = max(0.0, start_s - 0.5 / fps)
    try:
        reader = ffmpeg.read_frames(str(path), input_params=["-ss", f"{seek:.6f}"],
                                    output_params=[*_reader_passthrough_params(), "-frames:v", str(count)])
        meta = next(reader)
        width, height = meta["size"]
        frames = [np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3) for raw in reader]
    except (RuntimeError, OSError, StopIteration) as exc:
        detail = " ".join(str(exc).split())[:300]
        raise LeRobotDatasetError(f"cannot decode video {path}: {detail}; the file is corrupt or not an "
                                  "mp4: re-create the dataset") from None
    if len(frames) != count:
        raise LeRobotDatasetError(f"video {path} has {len(frames)} frames from {start_s:.4f}s where the episode "
                                  f"metadata needs {count}: the file is truncated or corrupt; re-create the dataset")
    return np.stack(frames)


# ---------------------------------------------------------------------------------------------
# Writer


def _check_features(features: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    checked: dict[str, dict[str, Any]] = {}
    for key, spec in features.items():
        if "/" in key or not key:
            raise LeRobotDatasetError(f"feature name {key!r}: names must be non-empty and contain no '/'")
        if key in INDEX_FEATURES:
            raise LeRobotDatasetError(f"feature {key!r} is written by the writer itself; leave it out")
        dtype, shape = spec.get("dtype"), tuple(int(n) for n in spec.get("shape", ()))
        if dtype == VIDEO_DTYPE:
            if len(shape) != 3 or shape[2] != 3 or shape[0] % 2 or shape[1] % 2:
                raise LeRobotDatasetError(f"video feature {key!r}: shape must be (height, width, 3) with even height "
                                          f"and width (H.264 yuv420p), got {shape}")
            names = spec.get("names") or ["height", "width", "channels"]
        elif dtype in NUMERIC_DTYPES:
            if len(shape) != 1 or shape[0] < 1:
                raise LeRobotDatasetError(f"feature {key!r}: shape must be (n,) (scalars are (1,)), got {shape}")
            names = spec.get("names")
        else:
            raise LeRobotDatasetError(f"feature {key!r}: dtype {dtype!r} is not one of "
                                      f"{[*NUMERIC_DTYPES, VIDEO_DTYPE]}")
        checked[key] = {"dtype": dtype, "shape": list(shape), "names": list(names) if names else None}
    return checked


def _update_chunk_file(chunk: int, file: int, chunks_size: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file == chunks_size - 1 else (chunk, file + 1)


def _stack_frames(frames: Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
    if isinstance(frames, Mapping):
        return {key: np.asarray(value) for key, value in frames.items()}
    if not frames:
        raise LeRobotDatasetError("an episode needs at least one frame")
    return {key: np.stack([np.asarray(frame[key]) for frame in frames]) for key in frames[0]}


class LeRobotDatasetWriter:
    """Write a LeRobotDataset v3.0 episode by episode; :meth:`finalize` puts it at ``root``.

    ``features``: LeRobot's feature dict, ``{name: {"dtype", "shape", "names"}}``, e.g.
    ``{"observation.state": {"dtype": "float32", "shape": (4,), "names": [...]},
    "observation.images.corner": {"dtype": "video", "shape": (64, 64, 3)}}``. Numeric features are
    vectors ``(n,)`` (scalars ``(1,)``); videos are ``(height, width, 3)`` uint8 frames.

    Use as a context manager (finalizes on success, discards everything on an error) or call
    :meth:`finalize` / :meth:`abort` yourself.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        *,
        fps: int,
        features: Mapping[str, Mapping[str, Any]],
        robot_type: str | None = None,
        video: VideoSettings | None = None,
        overwrite: bool = False,
        chunks_size: int = 1000,
        data_files_size_in_mb: float = 100,
        video_files_size_in_mb: float = 200,
    ) -> None:
        self.root = Path(root)
        if self.root.exists() and not overwrite:
            raise LeRobotDatasetError(f"{self.root} already exists; choose another folder or overwrite it "
                                      "(overwrite=True, --overwrite)")
        if int(fps) != fps or fps <= 0:
            raise LeRobotDatasetError(f"fps must be a positive integer (LeRobot stores it as one), got {fps}")
        self.fps = int(fps)
        self.features = _check_features(features)
        self.video_keys = [k for k, f in self.features.items() if f["dtype"] == VIDEO_DTYPE]
        if self.video_keys:
            _ffmpeg()
        self.robot_type = robot_type
        self.video = video or VideoSettings()
        self._limits = {"chunks_size": chunks_size, "data_files_size_in_mb": data_files_size_in_mb,
                        "video_files_size_in_mb": video_files_size_in_mb}
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(dir=self.root.parent, prefix=f".{self.root.name}.tmp-"))
        self._tasks: dict[str, int] = {}
        self._episodes: list[dict[str, Any]] = []
        self._episode_stats: list[dict] = []
        self._total_frames = 0
        self._data_file = (0, 0)
        self._data_bytes = 0
        self._data_writer: Any = None
        self._video_files = {key: (0, 0) for key in self.video_keys}
        self._video_writers: dict[str, _VideoFile] = {}
        self._closed = False

    @property
    def num_episodes(self) -> int:
        return len(self._episodes)

    @property
    def num_frames(self) -> int:
        return self._total_frames

    def add_episode(self, frames: Mapping[str, Any] | Sequence[Mapping[str, Any]], task: str) -> int:
        """Append one episode: ``frames`` maps every feature to its values over the episode
        (``[T, *shape]``), or is a sequence of per-frame dicts. ``task``: the instruction in words.
        Returns the episode's index."""
        if self._closed:
            raise LeRobotDatasetError(f"the writer of {self.root} is already finalized or aborted")
        if not isinstance(task, str) or not task.strip():
            raise LeRobotDatasetError(f"task must be a non-empty string, got {task!r}")
        columns = self._check_episode(_stack_frames(frames))
        length = len(next(iter(columns.values())))
        episode_index = len(self._episodes)
        task_index = self._tasks.setdefault(task, len(self._tasks))
        frame_index = np.arange(length, dtype=np.int64)
        columns.update({
            "timestamp": (frame_index / self.fps).astype(np.float32),
            "frame_index": frame_index,
            "episode_index": np.full(length, episode_index, dtype=np.int64),
            "index": np.arange(self._total_frames, self._total_frames + length, dtype=np.int64),
            "task_index": np.full(length, task_index, dtype=np.int64),
        })
        row: dict[str, Any] = {"episode_index": episode_index, "tasks": [task], "length": length}
        row.update(self._write_data(columns, length))
        for key in self.video_keys:
            row.update(self._write_video(key, columns[key]))
        stats = episode_stats(columns, {**self.features, **INDEX_FEATURES})
        self._episode_stats.append(stats)
        row.update({f"stats/{key}/{name}": np.asarray(value).tolist()
                    for key, item in stats.items() for name, value in item.items()})
        row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
        self._episodes.append(row)
        self._total_frames += length
        return episode_index

    def finalize(self) -> Path:
        """Close the files, write the metadata and move the dataset to ``root``; returns ``root``."""
        if self._closed:
            raise LeRobotDatasetError(f"the writer of {self.root} is already finalized or aborted")
        if not self._episodes:
            self.abort()
            raise LeRobotDatasetError(f"no episodes were added: nothing written to {self.root}")
        try:
            self._close_files()
            self._write_meta()
            replace_directory(self._tmp, self.root)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.root

    def abort(self) -> None:
        """Discard everything written so far; ``root`` is left as it was."""
        try:
            self._close_files()
        finally:
            self._closed = True
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> LeRobotDatasetWriter:
        return self

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        if self._closed:
            return
        if exc_type is None:
            self.finalize()
        else:
            self.abort()

    # ---- one episode ------------------------------------------------------------------------

    def _check_episode(self, columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        missing, extra = set(self.features) - set(columns), set(columns) - set(self.features)
        if missing or extra:
            raise LeRobotDatasetError(f"episode {len(self._episodes)}: missing features {sorted(missing)}, unknown "
                                      f"features {sorted(extra)}; the writer's features are {list(self.features)}")
        lengths = {key: len(value) if value.ndim else 0 for key, value in columns.items()}
        if len(set(lengths.values())) != 1 or not next(iter(lengths.values())):
            raise LeRobotDatasetError(f"episode {len(self._episodes)}: every feature needs the same number "
                                      f"(>= 1) of frames, got {lengths}")
        out = {}
        for key, spec in self.features.items():
            value = columns[key]
            shape = tuple(spec["shape"])
            if value.shape[1:] != shape and not (shape == (1,) and value.ndim == 1):
                raise LeRobotDatasetError(f"episode {len(self._episodes)}: feature {key!r} has frames of shape "
                                          f"{value.shape[1:]}, the features say {shape}")
            if spec["dtype"] == VIDEO_DTYPE:
                if value.dtype != np.uint8:
                    raise LeRobotDatasetError(f"episode {len(self._episodes)}: video feature {key!r} must be uint8 "
                                              f"RGB frames, got {value.dtype}")
                out[key] = value
            else:
                out[key] = value.reshape(len(value), -1).astype(spec["dtype"], copy=False)
        return out

    def _write_data(self, columns: dict[str, np.ndarray], length: int) -> dict[str, Any]:
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.table({key: _arrow_column(columns[key])
                          for key, spec in {**self.features, **INDEX_FEATURES}.items() if spec["dtype"] != VIDEO_DTYPE})
        limit = self._limits["data_files_size_in_mb"] * _MB
        if self._data_writer is not None and self._data_bytes + table.nbytes >= limit:
            self._data_writer.close()
            self._data_writer = None
            self._data_file = _update_chunk_file(*self._data_file, self._limits["chunks_size"])
        chunk, file = self._data_file
        if self._data_writer is None:
            path = self._tmp / DATA_PATH.format(chunk_index=chunk, file_index=file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self._data_writer = pq.ParquetWriter(path, table.schema, compression="snappy")
            self._data_bytes = 0
        self._data_writer.write_table(table)
        self._data_bytes += table.nbytes
        return {"data/chunk_index": chunk, "data/file_index": file,
                "dataset_from_index": self._total_frames, "dataset_to_index": self._total_frames + length}

    def _write_video(self, key: str, frames: np.ndarray) -> dict[str, Any]:
        writer = self._video_writers.get(key)
        if writer is not None and writer.size_mb() >= self._limits["video_files_size_in_mb"]:
            writer.close()
            writer = None
            self._video_files[key] = _update_chunk_file(*self._video_files[key], self._limits["chunks_size"])
        chunk, file = self._video_files[key]
        if writer is None:
            path = self._tmp / VIDEO_PATH.format(video_key=key, chunk_index=chunk, file_index=file)
            writer = self._video_writers[key] = _VideoFile(path, self.fps, self.video)
        start = writer.frames / self.fps
        writer.write(frames)
        return {f"videos/{key}/chunk_index": chunk, f"videos/{key}/file_index": file,
                f"videos/{key}/from_timestamp": start, f"videos/{key}/to_timestamp": writer.frames / self.fps}

    # ---- closing ----------------------------------------------------------------------------

    def _close_files(self) -> None:
        writers, self._video_writers = list(self._video_writers.values()), {}
        if self._data_writer is not None:
            writers.append(self._data_writer)
            self._data_writer = None
        errors = []
        for writer in writers:
            try:
                writer.close()
            except Exception as exc:  # close every file before reporting the first failure
                errors.append(exc)
        if errors:
            raise errors[0]

    def _write_meta(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        episodes_path = self._tmp / EPISODES_PATH.format(chunk_index=0, file_index=0)
        episodes_path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist(self._episodes), episodes_path, compression="snappy")
        pq.write_table(_tasks_table(list(self._tasks)), self._tmp / TASKS_PATH)
        write_json_atomic(self._tmp / STATS_PATH, _stats_to_json(aggregate_stats(self._episode_stats)))
        write_json_atomic(self._tmp / INFO_PATH, self._info())

    def _info(self) -> dict[str, Any]:
        features = {key: dict(spec) for key, spec in self.features.items()}
        for key in self.video_keys:
            height, width, channels = features[key]["shape"]
            features[key]["info"] = {
                "video.height": height, "video.width": width, "video.codec": "h264", "video.pix_fmt": "yuv420p",
                "video.is_depth_map": False, "video.fps": self.fps, "video.channels": channels, "has_audio": False,
            }
        features.update({key: dict(spec) for key, spec in INDEX_FEATURES.items()})
        return {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": self.robot_type,
            "total_episodes": len(self._episodes),
            "total_frames": self._total_frames,
            "total_tasks": len(self._tasks),
            **self._limits,
            "fps": self.fps,
            "splits": {"train": f"0:{len(self._episodes)}"},
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if self.video_keys else None,
            "features": features,
        }


def _arrow_column(values: np.ndarray) -> Any:
    """``[T, 1]`` -> a plain column, ``[T, D]`` -> a fixed-size list column (what LeRobot's
    ``datasets`` features give for shapes ``(1,)`` and ``(D,)``)."""
    import pyarrow as pa

    if values.ndim == 1 or values.shape[1] == 1:
        return pa.array(values.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])


def _tasks_table(tasks: list[str]) -> Any:
    """``meta/tasks.parquet`` as pandas writes ``DataFrame({"task_index": ...}, index=tasks)``:
    LeRobot reads it with pandas and looks tasks up by that index."""
    import pyarrow as pa

    pandas_meta = {
        "index_columns": [_PANDAS_INDEX_COLUMN],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
             "metadata": None},
            {"name": None, "field_name": _PANDAS_INDEX_COLUMN, "pandas_type": "unicode", "numpy_type": "object",
             "metadata": None},
        ],
        "attributes": {},
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    schema = pa.schema([("task_index", pa.int64()), (_PANDAS_INDEX_COLUMN, pa.string())],
                       metadata={b"pandas": json.dumps(pandas_meta).encode()})
    return pa.table({"task_index": np.arange(len(tasks), dtype=np.int64), _PANDAS_INDEX_COLUMN: tasks},
                    schema=schema)


# ---------------------------------------------------------------------------------------------
# Reader


def load_info(root: Path) -> dict[str, Any]:
    """``meta/info.json`` of the dataset at ``root``, checked to be a v3.0 dataset."""
    path = root / INFO_PATH
    if not path.is_file():
        raise LeRobotDatasetError(f"{path} not found: {root} is not a LeRobot dataset (create one with "
                                  "`infinirl demos metaworld --out DIR`, or point at the dataset's root folder)")
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise LeRobotDatasetError(f"{path} is not valid JSON ({exc}): the dataset is corrupt; re-create it") from None
    if not isinstance(info, dict):
        raise LeRobotDatasetError(f"{path} must hold a JSON object, got {type(info).__name__}: re-create the dataset")
    version = info.get("codebase_version")
    if version != CODEBASE_VERSION:
        raise LeRobotDatasetError(f"{path}: codebase_version {version!r} is not supported (this reader reads "
                                  f"{CODEBASE_VERSION!r}); convert older datasets with LeRobot's "
                                  "`python -m lerobot.datasets.v30.convert_dataset_v21_to_v30`")
    for key in ("fps", "features", "data_path", "total_frames", "total_episodes"):
        if key not in info:
            raise LeRobotDatasetError(f"{path} has no {key!r} key: the dataset is corrupt; re-create it")
    return info


def _read_parquet_files(folder: Path, what: str, columns: list[str] | None = None) -> Any:
    import pyarrow as pa
    import pyarrow.parquet as pq

    paths = sorted(folder.glob("*/*.parquet"))
    if not paths:
        raise LeRobotDatasetError(f"no parquet file under {folder}: the dataset's {what} are missing")
    tables = []
    for path in paths:
        try:
            tables.append(pq.read_table(path, columns=columns))
        except (pa.ArrowException, OSError) as exc:
            raise LeRobotDatasetError(f"cannot read {path} ({' '.join(str(exc).split())[:200]}): the dataset is "
                                      "corrupt; re-create it") from None
    return pa.concat_tables(tables, promote_options="default") if len(tables) > 1 else tables[0]


def _numpy_column(column: Any, shape: Sequence[int]) -> np.ndarray:
    import pyarrow as pa

    array = column.combine_chunks()
    if pa.types.is_list(array.type) or pa.types.is_fixed_size_list(array.type) or pa.types.is_large_list(array.type):
        return array.flatten().to_numpy(zero_copy_only=False).reshape(len(array), *shape)
    return array.to_numpy(zero_copy_only=False)


def _read_tasks(path: Path) -> list[str]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not path.is_file():
        raise LeRobotDatasetError(f"{path} not found: the dataset's task list is missing; re-create the dataset")
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise LeRobotDatasetError(f"cannot read {path} ({exc}): the dataset is corrupt; re-create it") from None
    index_columns = (table.schema.pandas_metadata or {}).get("index_columns", [])
    names = [c for c in (*index_columns, "task") if isinstance(c, str) and c in table.column_names]
    if not names or "task_index" not in table.column_names:
        raise LeRobotDatasetError(f"{path} has no task strings and task_index column: re-create the dataset")
    tasks = dict(zip(table.column("task_index").to_pylist(), table.column(names[0]).to_pylist()))
    return [tasks[i] for i in range(len(tasks))]


class LeRobotDatasetReader:
    """Read a LeRobotDataset v3.0 folder (ours or LeRobot's, with video features).

    ``reader[i]``: frame ``i`` as a dict: every feature as a numpy array of its shape (scalars
    ``(1,)`` as numpy scalars), video frames as uint8 ``[H, W, 3]``, and ``"task"`` (the
    instruction). ``reader.episode(e)``: the whole episode, every feature stacked over time
    ``[T, ...]``. Arrays are read-only views. The numeric columns of all frames are loaded when
    the reader opens (a few hundred bytes a frame); videos are decoded per episode when asked
    for, and the ``episode_cache`` most recently decoded episodes are kept, so reading the frames
    of one episode in turn decodes its video once.
    """

    def __init__(self, root: str | os.PathLike, *, episode_cache: int = 4) -> None:
        self.root = Path(root)
        self.info = load_info(self.root)
        self.fps = int(self.info["fps"])
        self.features: dict[str, dict[str, Any]] = self.info["features"]
        self.video_keys = [k for k, f in self.features.items() if f.get("dtype") == VIDEO_DTYPE]
        self.tasks = _read_tasks(self.root / TASKS_PATH)
        self._episodes = self._read_episodes()
        self._data = self._read_data()
        self._check_videos()
        self._cache: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        self._cache_size = max(1, episode_cache)

    @property
    def num_frames(self) -> int:
        return len(self._data["index"])

    @property
    def num_episodes(self) -> int:
        return len(self._episodes["episode_index"])

    def __len__(self) -> int:
        return self.num_frames

    @property
    def stats(self) -> dict[str, dict[str, np.ndarray]]:
        path = self.root / STATS_PATH
        if not path.is_file():
            return {}
        try:
            stats = json.loads(path.read_text())
            return {key: {name: np.asarray(value) for name, value in item.items()} for key, item in stats.items()}
        except (json.JSONDecodeError, UnicodeDecodeError, AttributeError, ValueError) as exc:
            # Cut off mid-write or edited by hand: named here, not as a traceback where it is used.
            raise LeRobotDatasetError(f"{path} is not a JSON object of feature -> statistic -> values "
                                      f"({' '.join(str(exc).split())[:200]}): the dataset is corrupt; re-create it") \
                from None

    def episode_range(self, episode: int) -> tuple[int, int]:
        """The frame indices ``[from, to)`` of ``episode``."""
        self._check_episode_index(episode)
        return int(self._episodes["dataset_from_index"][episode]), int(self._episodes["dataset_to_index"][episode])

    def episode(self, episode: int) -> dict[str, Any]:
        """Every feature of ``episode`` stacked over its frames, plus ``"task"``."""
        start, stop = self.episode_range(episode)
        out: dict[str, Any] = {key: values[start:stop] for key, values in self._data.items()}
        out.update(self._episode_videos(episode))
        out["task"] = self.tasks[int(self._data["task_index"][start])]
        return out

    def __getitem__(self, index: int) -> dict[str, Any]:
        index = int(index)
        if not 0 <= index < self.num_frames:
            raise IndexError(f"frame {index} out of range: the dataset at {self.root} has {self.num_frames} frames")
        out: dict[str, Any] = {key: values[index] for key, values in self._data.items()}
        if self.video_keys:
            episode = int(self._data["episode_index"][index])
            offset = index - int(self._episodes["dataset_from_index"][episode])
            out.update({key: frames[offset] for key, frames in self._episode_videos(episode).items()})
        out["task"] = self.tasks[int(self._data["task_index"][index])]
        return out

    # ---- loading ----------------------------------------------------------------------------

    def _read_episodes(self) -> dict[str, list]:
        import pyarrow.parquet as pq

        folder = self.root / "meta/episodes"
        first = sorted(folder.glob("*/*.parquet"))
        columns = None
        if first:  # the per-episode stats columns are many and unused here
            columns = [c for c in pq.read_schema(first[0]).names if not c.startswith("stats/")]
        table = _read_parquet_files(folder, "episode metadata", columns)
        episodes = {name: table.column(name).to_pylist() for name in table.column_names}
        required = ["episode_index", "length", "dataset_from_index", "dataset_to_index"]
        for key in self.video_keys:
            required += [f"videos/{key}/chunk_index", f"videos/{key}/file_index", f"videos/{key}/from_timestamp"]
        missing = [name for name in required if name not in episodes]
        if missing:
            raise LeRobotDatasetError(f"{folder}: episode metadata lacks columns {missing}; re-create the dataset")
        if episodes["episode_index"] != list(range(len(episodes["episode_index"]))):
            raise LeRobotDatasetError(f"{folder}: episode_index is not 0, 1, 2, ...: the metadata is corrupt")
        return episodes

    def _read_data(self) -> dict[str, np.ndarray]:
        keys = [k for k, f in self.features.items() if f.get("dtype") != VIDEO_DTYPE and f.get("dtype") in
                (*NUMERIC_DTYPES, "int8", "int16", "uint8", "float16")]
        table = _read_parquet_files(self.root / "data", "frames")
        missing = [k for k in keys if k not in table.column_names]
        if missing:
            raise LeRobotDatasetError(f"{self.root / 'data'}: the frame files lack the columns {missing} that "
                                      f"{INFO_PATH} lists; the dataset is corrupt")
        data = {}
        for key in keys:
            shape = tuple(self.features[key]["shape"])
            data[key] = _numpy_column(table.column(key), () if shape == (1,) else shape)
            data[key].flags.writeable = False
        if not np.array_equal(data["index"], np.arange(len(data["index"]))):
            raise LeRobotDatasetError(f"{self.root / 'data'}: the frames' index column is not 0, 1, 2, ... in file "
                                      "order; the dataset is corrupt")
        task_index = data.get("task_index", np.zeros(0, dtype=np.int64))
        if len(task_index) and (task_index.min() < 0 or task_index.max() >= len(self.tasks)):
            bad = int(task_index.max() if task_index.max() >= len(self.tasks) else task_index.min())
            raise LeRobotDatasetError(f"{self.root / 'data'}: a frame has task_index {bad}, but {TASKS_PATH} lists "
                                      f"{len(self.tasks)} tasks; the dataset is corrupt")
        return data

    def _video_path(self, key: str, episode: int) -> Path:
        template = self.info.get("video_path") or VIDEO_PATH
        chunk = self._episodes[f"videos/{key}/chunk_index"][episode]
        return self.root / template.format(video_key=key, chunk_index=chunk,
                                           file_index=self._episodes[f"videos/{key}/file_index"][episode])

    def _check_videos(self) -> None:
        for key in self.video_keys:
            for episode in range(self.num_episodes):
                path = self._video_path(key, episode)
                if not path.is_file():
                    raise LeRobotDatasetError(f"video {path} (feature {key!r}, episode {episode}) is missing: copy "
                                              "the dataset's videos/ folder along with it, or re-create the dataset")

    def _check_episode_index(self, episode: int) -> None:
        if not 0 <= episode < self.num_episodes:
            raise IndexError(f"episode {episode} out of range: the dataset at {self.root} has "
                             f"{self.num_episodes} episodes")

    def _episode_videos(self, episode: int) -> dict[str, np.ndarray]:
        if episode in self._cache:
            self._cache.move_to_end(episode)
            return self._cache[episode]
        length = int(self._episodes["length"][episode])
        frames = {}
        for key in self.video_keys:
            start = float(self._episodes[f"videos/{key}/from_timestamp"][episode])
            frames[key] = read_video_frames(self._video_path(key, episode), start, length, self.fps)
        for array in frames.values():
            array.flags.writeable = False
        self._cache[episode] = frames
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return frames
