"""Success labels on disk: one ``.npz`` per marked episode, as
:class:`~infinirl.realworld.intervention.human_reward.SuccessLabelWriter` writes them (``label``
int8 ``[T]``, ``state`` ``[T, D]``, each ``pixels.<camera>`` ``[T, H, W, 3]``).

Observations of one episode are near copies of each other, so the validation split holds out whole
episodes (never frames of an episode trained on), drawn separately from the episodes that hold a
success and from those that do not, so both classes are held out. A human marks one success per
episode, so positives are rare: training batches draw half of their rows from each class.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["LABEL_KEY", "LabelledEpisodes", "balanced_batch", "load_labels", "split_episodes"]

LABEL_KEY = "label"
_FIX = "record marked episodes with interventions.labels=true (they land in <output_dir>/success_labels)"


@dataclass(frozen=True, kw_only=True)
class LabelledEpisodes:
    """Every labelled observation of a folder, episodes one after another."""

    folder: str
    files: tuple[str, ...]
    """The episodes' file names, in the order their rows appear."""
    obs: dict[str, np.ndarray]
    """Observation key -> ``[N, ...]``."""
    labels: np.ndarray
    """``[N]`` int8: 1 success, 0 not."""
    episode: np.ndarray
    """``[N]`` int64: the index in ``files`` of each row's episode."""

    @property
    def shapes(self) -> dict[str, tuple[int, ...]]:
        return {key: tuple(int(size) for size in value.shape[1:]) for key, value in self.obs.items()}

    def rows_of(self, episodes: Sequence[int] | np.ndarray) -> np.ndarray:
        return np.flatnonzero(np.isin(self.episode, np.asarray(episodes, np.int64)))


def _label_files(folder: str) -> list[str]:
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"labels folder {folder} does not exist; {_FIX}")
    files = sorted(name for name in os.listdir(folder) if name.endswith(".npz"))
    if not files:
        raise ValueError(f"labels folder {folder} holds no .npz label files; {_FIX}")
    return files


def load_labels(folder: str, keys: Sequence[str] | None = None) -> LabelledEpisodes:
    """Read every ``.npz`` of ``folder`` (sorted by name); ``keys``: the observation keys to keep
    (None: all the first file holds). A file that lacks a key, or whose shapes differ from the
    first file's, fails naming that file."""
    files = _label_files(folder)
    obs: dict[str, list[np.ndarray]] = {}
    labels, episode = [], []
    shapes: dict[str, tuple[int, ...]] = {}
    for index, name in enumerate(files):
        path = os.path.join(folder, name)
        with np.load(path) as data:
            held = [key for key in data.files if key != LABEL_KEY]
            if LABEL_KEY not in data.files:
                raise ValueError(f"{path} has no {LABEL_KEY!r} array (it holds {held}); it is not a success label "
                                 "file: keep only SuccessLabelWriter's files in the folder")
            wanted = list(keys) if keys is not None else held
            missing = [key for key in wanted if key not in data.files]
            if missing:
                raise ValueError(f"{path} has no {missing}; it holds {held}: choose the observation keys from those")
            label = np.asarray(data[LABEL_KEY]).astype(np.int8).reshape(-1)
            for key in wanted:
                value = np.asarray(data[key])
                shape = tuple(value.shape[1:])
                if len(value) != len(label):
                    raise ValueError(f"{path}: {key!r} has {len(value)} rows and {LABEL_KEY!r} {len(label)}; the file "
                                     "is damaged: delete it")
                if shapes.setdefault(key, shape) != shape:
                    raise ValueError(f"{path}: {key!r} is {shape} per row, {files[0]} has {shapes[key]}; labels of "
                                     "one classifier come from one observation layout: keep one in the folder")
                obs.setdefault(key, []).append(value)
        labels.append(label)
        episode.append(np.full(len(label), index, np.int64))
    if keys is None and not obs:
        raise ValueError(f"{os.path.join(folder, files[0])} holds labels but no observations")
    return LabelledEpisodes(folder=folder, files=tuple(files), obs={k: np.concatenate(v) for k, v in obs.items()},
                            labels=np.concatenate(labels), episode=np.concatenate(episode))


def split_episodes(data: LabelledEpisodes, val_fraction: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(training rows, validation rows)``: of the episodes that hold a success, and separately of
    those that do not, ``round(val_fraction * n)`` (at least one, and never all of them, when a group
    has two or more and ``val_fraction > 0``) are held out, drawn by ``seed``."""
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    rng = np.random.default_rng([seed, 0x5C1A])
    has_success = np.zeros(len(data.files), bool)
    has_success[data.episode[data.labels == 1]] = True
    held_out: list[np.ndarray] = []
    for group in (np.flatnonzero(has_success), np.flatnonzero(~has_success)):
        count = len(group)
        if val_fraction == 0.0 or count < 2:
            continue
        take = min(count - 1, max(1, int(round(val_fraction * count))))
        held_out.append(rng.permutation(group)[:take])
    val_episodes = np.sort(np.concatenate(held_out)) if held_out else np.zeros(0, np.int64)
    val = data.rows_of(val_episodes)
    train = np.setdiff1d(np.arange(len(data.labels)), val)
    return train, val


def balanced_batch(labels: np.ndarray, rows: np.ndarray, batch_size: int, rng: np.random.Generator) -> np.ndarray:
    """``batch_size`` rows drawn with replacement from ``rows``: half (rounded down) successes, the
    rest non-successes, shuffled."""
    positives, negatives = rows[labels[rows] == 1], rows[labels[rows] == 0]
    if not len(positives) or not len(negatives):
        raise ValueError(f"a balanced batch needs both classes; the rows hold {len(positives)} successes and "
                         f"{len(negatives)} non-successes")
    half = batch_size // 2
    batch = np.concatenate([rng.choice(positives, half), rng.choice(negatives, batch_size - half)])
    return rng.permutation(batch)
