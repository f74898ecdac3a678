"""A preallocated ring-buffer replay memory for off-policy RL (SAC), with exact save/restore.

* **Storage.** One numpy array per field, allocated once at ``capacity`` rows (no per-transition
  Python objects, no growth). ``add`` writes a batch of rows at the write position and wraps
  around, overwriting the oldest rows; a batch larger than the capacity keeps its newest rows.
* **Sampling.** Uniform with replacement over the filled rows, from the buffer's own seeded
  ``numpy.random.Generator`` (PCG64): the sequence of mini-batches is a function of the seed and
  the sequence of ``add`` calls only, never of global RNG state or of other components.
* **Exact resume.** :meth:`ReplayBuffer.state_dict` holds the filled rows, the write position,
  the counters and the generator's state; :meth:`ReplayBuffer.save` writes it as one ``.npz``
  file atomically (a temporary file in the same folder, ``fsync``, then ``os.replace``), so a
  crash mid-save leaves the previous file intact. A buffer restored with :meth:`ReplayBuffer.load`
  samples exactly the mini-batches the original would have.

Fields are declared up front as ``name -> (shape, dtype)`` of ONE row (nested observation dicts
are flattened by the caller, e.g. ``obs.state``). Everything here is numpy only, so the buffer
imports cheaply in any process.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

import numpy as np

from infinirl.utils.atomic import atomic_open

__all__ = ["FieldSpec", "ReplayBuffer"]

FieldSpec = tuple[tuple[int, ...], str]
"""``(shape of one row, numpy dtype name)``, e.g. ``((4,), "float32")``."""

_META_KEY = "__replay_buffer_meta__"
_FORMAT = 1


class ReplayBuffer:
    """``capacity`` rows of the declared fields; ``add`` batches, ``sample`` uniform mini-batches.

    Args:
        capacity: rows kept; older rows are overwritten first once full.
        fields: ``name -> (row shape, dtype)``.
        seed: seeds the sampling generator (an int or a sequence of ints, numpy's SeedSequence
            entropy), so two buffers built with the same seed and fed the same rows sample the
            same indices.
    """

    def __init__(self, capacity: int, fields: Mapping[str, FieldSpec], seed: int | list[int] = 0):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if not fields:
            raise ValueError("a replay buffer needs at least one field")
        self.capacity = int(capacity)
        self.fields: dict[str, FieldSpec] = {
            name: (tuple(int(d) for d in shape), np.dtype(dtype).name) for name, (shape, dtype) in fields.items()
        }
        self._data = {name: np.zeros((self.capacity, *shape), dtype=dtype)
                      for name, (shape, dtype) in self.fields.items()}
        self._rng = np.random.default_rng(seed)
        self._pos = 0  # next row to write
        self._size = 0  # filled rows
        self.added = 0  # rows ever added (a position in the data stream, for resume and metrics)

    # ------------------------------------------------------------------ writing / reading
    def __len__(self) -> int:
        return self._size

    @property
    def full(self) -> bool:
        return self._size == self.capacity

    @property
    def nbytes(self) -> int:
        """Bytes allocated for storage (all ``capacity`` rows)."""
        return sum(array.nbytes for array in self._data.values())

    def add(self, batch: Mapping[str, Any]) -> int:
        """Append the rows of ``batch`` (every declared field, same leading length ``n``); returns ``n``.

        Rows are cast to the field's dtype; a wrong field set or row shape raises ``ValueError``
        naming the field and the expected shape.
        """
        missing = set(self.fields) - set(batch)
        extra = set(batch) - set(self.fields)
        if missing or extra:
            raise ValueError(f"replay batch fields differ from the buffer's: missing {sorted(missing)}, "
                             f"unknown {sorted(extra)} (buffer fields: {sorted(self.fields)})")
        arrays = {name: np.asarray(batch[name]) for name in self.fields}
        lengths = {name: (array.shape[0] if array.ndim else -1) for name, array in arrays.items()}
        n = next(iter(lengths.values()))
        for name, array in arrays.items():
            shape = self.fields[name][0]
            if array.ndim == 0 or array.shape[1:] != shape or lengths[name] != n:
                raise ValueError(f"replay field {name!r}: expected rows of shape {shape} and {n} rows, "
                                 f"got an array of shape {array.shape}")
        if n == 0:
            return 0
        if n > self.capacity:  # only the newest `capacity` rows can stay; write those
            skipped = n - self.capacity
            arrays = {name: array[skipped:] for name, array in arrays.items()}
            self._pos = (self._pos + skipped) % self.capacity
            self.added += skipped
            n = self.capacity
        first = min(n, self.capacity - self._pos)  # rows before the wrap
        for name, array in arrays.items():
            target = self._data[name]
            target[self._pos:self._pos + first] = array[:first]
            if first < n:
                target[:n - first] = array[first:]
        self._pos = (self._pos + n) % self.capacity
        self._size = min(self._size + n, self.capacity)
        self.added += n
        return n

    def sample_indices(self, batch_size: int) -> np.ndarray:
        """``batch_size`` row indices drawn uniformly (with replacement) from the filled rows."""
        if self._size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        return self._rng.integers(0, self._size, size=batch_size)

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        """A uniform mini-batch: ``name -> [batch_size, *shape]`` (fresh arrays, safe to keep)."""
        return self.gather(self.sample_indices(batch_size))

    def gather(self, indices: np.ndarray) -> dict[str, np.ndarray]:
        return {name: array[indices] for name, array in self._data.items()}

    def rows(self) -> dict[str, np.ndarray]:
        """Every filled row, oldest first (copies), e.g. to inspect or compare buffers."""
        order = (np.arange(self._size) + (self._pos if self.full else 0)) % self.capacity
        return self.gather(order)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Everything :meth:`load_state_dict` needs to continue exactly (filled rows, write
        position, counters, generator state); arrays are views of the storage, not copies."""
        return {
            "format": _FORMAT,
            "capacity": self.capacity,
            "fields": {name: [list(shape), dtype] for name, (shape, dtype) in self.fields.items()},
            "pos": self._pos,
            "size": self._size,
            "added": self.added,
            "rng": self._rng.bit_generator.state,
            "data": {name: array[:self._size] for name, array in self._data.items()},
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        fields = {name: (tuple(shape), np.dtype(dtype).name) for name, (shape, dtype) in state["fields"].items()}
        if int(state["capacity"]) != self.capacity or fields != self.fields:
            raise ValueError(
                f"replay buffer state has capacity {state['capacity']} and fields {fields}; this buffer has "
                f"capacity {self.capacity} and fields {self.fields}. Resume with the config the run was started with."
            )
        size = int(state["size"])
        for name, rows in state["data"].items():
            if len(rows) != size:
                raise ValueError(f"replay buffer state: field {name!r} has {len(rows)} rows, expected {size}")
            self._data[name][:size] = rows
            self._data[name][size:] = 0
        self._pos, self._size, self.added = int(state["pos"]), size, int(state["added"])
        self._rng.bit_generator.state = state["rng"]

    def save(self, path: str) -> str:
        """Write :meth:`state_dict` to ``path`` (an ``.npz`` file) atomically; returns ``path``."""
        state = self.state_dict()
        meta = {key: value for key, value in state.items() if key != "data"}
        arrays = {f"data/{name}": rows for name, rows in state["data"].items()}
        arrays[_META_KEY] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        with atomic_open(path, "wb", durable=True) as handle:  # a file object: np.savez adds no ".npz"
            np.savez(handle, **arrays)
        return path

    def load(self, path: str) -> None:
        """Restore the state :meth:`save` wrote (into this buffer, which must match its config)."""
        with np.load(path, allow_pickle=False) as archive:
            meta = json.loads(archive[_META_KEY].tobytes().decode())
            if meta.get("format") != _FORMAT:
                raise ValueError(f"{path}: replay buffer format {meta.get('format')}, expected {_FORMAT}")
            meta["data"] = {name: archive[f"data/{name}"] for name in meta["fields"]}
            self.load_state_dict(meta)

    @classmethod
    def from_file(cls, path: str) -> ReplayBuffer:
        """A buffer rebuilt entirely from a file :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as archive:
            meta = json.loads(archive[_META_KEY].tobytes().decode())
        buffer = cls(meta["capacity"], {name: (tuple(shape), dtype) for name, (shape, dtype) in meta["fields"].items()})
        buffer.load(path)
        return buffer

    def digest(self) -> str:
        """sha256 over the filled rows (oldest first), the counters and the generator state: equal
        digests mean the buffers hold the same data and will sample the same mini-batches."""
        h = hashlib.sha256()
        h.update(json.dumps({"pos": self._pos, "size": self._size, "added": self.added,
                             "rng": self._rng.bit_generator.state}, sort_keys=True, default=str).encode())
        for name, rows in sorted(self.rows().items()):
            h.update(name.encode())
            h.update(np.ascontiguousarray(rows).tobytes())
        return h.hexdigest()
