"""What one episode holds: its fields, declared up front, and the check every appended episode passes.

An episode of ``T`` steps holds ``T + 1`` rows of every observation field (the observation before
each step and the final one) and ``T`` rows of every step field (action, reward, done, policy
version, ...). Sampling pairs observation row ``t`` (``obs.<name>``) with row ``t + 1``
(``next_obs.<name>``) of the same episode, so ``next_obs`` never crosses an episode boundary.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from infinirl.components.replay_buffer import FieldSpec

__all__ = ["EpisodeSpec", "FieldSpec"]

_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")  # field names become file names


def _normalise(fields: Mapping[str, FieldSpec], kind: str) -> dict[str, FieldSpec]:
    out = {}
    for name, (shape, dtype) in fields.items():
        if not _NAME.match(name):
            raise ValueError(f"replay {kind} field {name!r}: names may hold letters, digits, '_', '.', '-' only "
                             f"(they name files on disk)")
        out[name] = (tuple(int(d) for d in shape), np.dtype(dtype).name)
    return out


@dataclass(frozen=True, kw_only=True)
class EpisodeSpec:
    """``observations``: ``name -> (row shape, dtype)`` with ``T + 1`` rows per episode;
    ``steps``: ``name -> (row shape, dtype)`` with ``T`` rows per episode."""

    observations: Mapping[str, FieldSpec]
    steps: Mapping[str, FieldSpec] = field(default_factory=dict)

    def __post_init__(self):
        observations = _normalise(self.observations, "observation")
        steps = _normalise(self.steps, "step")
        if not observations:
            raise ValueError("an EpisodeSpec needs at least one observation field")
        clash = sorted(set(observations) & set(steps))
        if clash:
            raise ValueError(f"replay fields {clash} are declared both as observation and as step fields")
        object.__setattr__(self, "observations", observations)
        object.__setattr__(self, "steps", steps)

    @property
    def fields(self) -> dict[str, FieldSpec]:
        """Every field, observations first, in declaration order (the order of the files and checksums)."""
        return {**self.observations, **self.steps}

    def rows(self, name: str, steps: int) -> int:
        """Rows of field ``name`` in an episode of ``steps`` steps."""
        return steps + 1 if name in self.observations else steps

    def row_bytes(self, name: str) -> int:
        shape, dtype = self.fields[name]
        return int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize

    def batch_fields(self) -> dict[str, FieldSpec]:
        """The rows of a sampled batch: ``obs.<name>``, ``next_obs.<name>``, then every step field."""
        return ({f"obs.{n}": spec for n, spec in self.observations.items()}
                | {f"next_obs.{n}": spec for n, spec in self.observations.items()} | dict(self.steps))

    def batch_keys(self) -> list[str]:
        return list(self.batch_fields())

    def check_episode(self, episode: Mapping[str, Any]) -> tuple[int, dict[str, np.ndarray]]:
        """``(T, contiguous arrays)`` of a valid episode; a ``ValueError`` naming the field otherwise.

        Dtypes must match exactly (no silent cast: a float64 image would double the disk use)."""
        missing, extra = set(self.fields) - set(episode), set(episode) - set(self.fields)
        if missing or extra:
            raise ValueError(f"replay episode fields differ from the store's: missing {sorted(missing)}, unknown "
                             f"{sorted(extra)} (declared: observations {list(self.observations)}, steps "
                             f"{list(self.steps)})")
        implied = {name: (np.shape(episode[name])[0] - self.rows(name, 0) if np.ndim(episode[name]) else -1)
                   for name in self.fields}  # the steps each field's row count says
        steps = max(set(implied.values()), key=list(implied.values()).count)  # the majority
        odd = {name: n for name, n in implied.items() if n != steps}
        if steps < 1 or odd:
            raise ValueError(f"replay episode: fields {sorted(odd) or sorted(implied)} disagree on the number of steps "
                             f"({implied}; observation fields hold T + 1 rows, step fields T, T >= 1)")
        arrays = {}
        for name, (shape, dtype) in self.fields.items():
            array = np.asarray(episode[name])
            rows = self.rows(name, steps)
            kind = "observation" if name in self.observations else "step"
            if array.shape != (rows, *shape):
                raise ValueError(f"replay {kind} field {name!r}: expected shape {(rows, *shape)} ({rows} rows for "
                                 f"{steps} steps), got {array.shape}")
            if array.dtype != np.dtype(dtype):
                raise ValueError(f"replay {kind} field {name!r}: expected dtype {dtype}, got {array.dtype}; "
                                 f"cast it with .astype({dtype!r}) first")
            arrays[name] = np.ascontiguousarray(array)
        return steps, arrays

    # ------------------------------------------------------------------ persistence
    def to_json(self) -> dict:
        return {"observations": {n: [list(s), d] for n, (s, d) in self.observations.items()},
                "steps": {n: [list(s), d] for n, (s, d) in self.steps.items()}}

    @classmethod
    def from_json(cls, data: Mapping) -> EpisodeSpec:
        return cls(observations={n: (tuple(s), d) for n, (s, d) in data["observations"].items()},
                   steps={n: (tuple(s), d) for n, (s, d) in data["steps"].items()})
