"""Intervened stretches of an episode as episodes of their own: the human's corrections as
demonstrations (RLPD's demonstrations buffer takes them beside the scripted ones)."""

from __future__ import annotations

import numpy as np

__all__ = ["intervened_runs", "intervened_segments"]


def intervened_runs(intervened: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` step ranges of consecutive intervened steps, in order."""
    flags = np.concatenate([[False], np.asarray(intervened).reshape(-1) != 0, [False]])
    edges = np.flatnonzero(flags[1:] != flags[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2])]


def intervened_segments(episode: dict[str, np.ndarray], obs_keys: frozenset[str] | None = None) -> list[dict]:
    """One episode per run of intervened steps ``[a, b)``: observations ``a..b`` (``b - a + 1`` rows: the
    state after the human's last action is the last transition's next observation) and the step fields
    of steps ``a..b-1``. ``obs_keys``: the observation fields (default: ``state`` and ``pixels.*``)."""
    steps = len(episode["intervened"])
    keys = obs_keys if obs_keys is not None else frozenset(k for k in episode if k == "state" or
                                                           k.startswith("pixels."))
    segments = []
    for start, stop in intervened_runs(episode["intervened"]):
        segment = {}
        for key, value in episode.items():
            if key in keys:
                segment[key] = np.ascontiguousarray(value[start:stop + 1])
            elif len(value) == steps:
                segment[key] = np.ascontiguousarray(value[start:stop])
            else:
                raise ValueError(f"episode field {key!r} has {len(value)} rows; steps have {steps}, "
                                 f"observations {steps + 1}")
        segments.append(segment)
    return segments
