"""Benchmark: the persistent replay store (`infinirl.realworld.replay.ReplayStore`) vs a pure-disk
memory-mapped buffer and vs an in-memory numpy buffer holding the same pixel transitions.

Data: ``--episodes`` episodes of ``--steps`` steps; observations ``pixels`` (84x84x3 uint8) and
``proprio`` (8 float32), T + 1 rows per episode; step fields ``action`` (4 float32), ``reward``,
``done``. Every implementation lays the rows out the same way (one array per field, episode after
episode) and gathers a batch of ``--batch`` transitions (obs and next_obs of each observation
field, and each step field) at the same positions, drawn by the store's seeded sampler.

  ours:    ReplayStore with a cache of ``--cache-mb`` (default: all of the data), reopened after the
           appends as a restarted learner would (the newest sealed segments load into the cache;
           the open segment is read through memory maps).
  disk:    np.memmap of one file per field, no cache of its own. "Pure disk" here: before every
           batch the maps are dropped and ``posix_fadvise(POSIX_FADV_DONTNEED)`` asks the kernel
           to drop the files' pages from its page cache, so the batch's rows are read from the
           device (dropping the page cache system-wide needs root). The same is done to the
           store's files before each of its batches (its cache is process memory, unaffected).
           The advice drops clean pages only: the files are fsynced first.
  memory:  the same arrays in process memory (numpy fancy indexing).
  (info) ours_small_cache: the store with a cache of ``--small-cache-fraction`` of the data,
           whose other segments are read from disk like ``disk``.

Append throughput: ``ours`` appends every episode (checked, checksummed, fsynced once committed:
``durable=True``); ``disk_write`` is the same bytes written sequentially into the memmap files
with one fsync at the end, for scale.

    python benchmarks/replay_buffer.py                      # ~1 minute
    python benchmarks/replay_buffer.py --episodes 1000 --batches 200   # larger (about 2 GiB on disk)

The last stdout line is ONE JSON object: {"benchmark": "replay_buffer", "ratios": {"sample_vs_disk":
ours batches/s / disk batches/s, "sample_vs_memory": ours batches/s / memory batches/s (= memory
time / our time: >= 0.67 means within 1.5x of in-memory)}, "targets": {...}, "results": {...}}.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time

import numpy as np

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import add_record_argument, conclude, concluded, device_description  # noqa: E402

from infinirl.realworld.replay import EpisodeSpec, ReplayStore, SamplingSpec, StoreOptions  # noqa: E402

MIB = 1 << 20
SPEC = EpisodeSpec(observations={"pixels": ((84, 84, 3), "uint8"), "proprio": ((8,), "float32")},
                   steps={"action": ((4,), "float32"), "reward": ((), "float32"), "done": ((), "bool")})
TARGETS = {"sample_vs_disk": 3.0, "sample_vs_memory": 0.67}


def make_episode(rng: np.random.Generator, steps: int) -> dict[str, np.ndarray]:
    return {"pixels": rng.integers(0, 256, (steps + 1, 84, 84, 3), dtype=np.uint8),
            "proprio": rng.standard_normal((steps + 1, 8), dtype=np.float32),
            "action": rng.uniform(-1, 1, (steps, 4)).astype(np.float32),
            "reward": rng.standard_normal(steps, dtype=np.float32), "done": np.arange(steps) == steps - 1}


def drop_pages(files: list[str]) -> None:
    for path in files:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


class ArrayBuffer:
    """The baselines: one array per field (rows laid out like the store's), in memory or mapped."""

    def __init__(self, arrays: dict[str, np.ndarray], steps: int):
        self.arrays, self.steps = arrays, steps

    def gather(self, positions: np.ndarray) -> dict[str, np.ndarray]:
        episode, t = np.divmod(positions, self.steps)
        obs_rows = episode * (self.steps + 1) + t
        out = {}
        for name in SPEC.observations:
            out[f"obs.{name}"] = self.arrays[name][obs_rows]
            out[f"next_obs.{name}"] = self.arrays[name][obs_rows + 1]
        for name in SPEC.steps:
            out[name] = self.arrays[name][positions]
        return out


def write_disk_files(folder: str, episodes: int, steps: int, seed: int) -> tuple[dict[str, str], float]:
    """The disk baseline's files (the same rows as the store's); returns the paths and write seconds."""
    rng = np.random.default_rng(seed)
    paths = {name: os.path.join(folder, f"{name}.bin") for name in SPEC.fields}
    handles = {name: open(path, "wb") for name, path in paths.items()}
    elapsed = 0.0
    for _ in range(episodes):
        episode = make_episode(rng, steps)
        start = time.perf_counter()
        for name, handle in handles.items():
            handle.write(episode[name].tobytes())
        elapsed += time.perf_counter() - start
    start = time.perf_counter()
    for handle in handles.values():
        handle.flush()
        os.fsync(handle.fileno())
        handle.close()
    return paths, elapsed + time.perf_counter() - start


def map_disk(paths: dict[str, str], rows_obs: int, rows_step: int) -> dict[str, np.ndarray]:
    out = {}
    for name, path in paths.items():
        shape, dtype = SPEC.fields[name]
        rows = rows_obs if name in SPEC.observations else rows_step
        out[name] = np.memmap(path, dtype=dtype, mode="r", shape=(rows, *shape))
    return out


def time_batches(gather, draws: list[np.ndarray], before_batch=None) -> float:
    """Seconds spent in ``gather`` over all draws (``before_batch`` runs untimed before each)."""
    total = 0.0
    for positions in draws:
        if before_batch is not None:
            before_batch()
        start = time.perf_counter()
        batch = gather(positions)
        total += time.perf_counter() - start
        assert len(batch["obs.pixels"]) == len(positions)
    return total


def rates(seconds: float, batches: int, batch: int, row_bytes: int) -> dict:
    return {"batches_per_s": round(batches / seconds, 2), "transitions_per_s": round(batches * batch / seconds),
            "mb_per_s": round(batches * batch * row_bytes / seconds / MIB, 1), "seconds": round(seconds, 3)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--batches", type=int, default=40, help="timed batches per implementation")
    parser.add_argument("--segment-mb", type=int, default=64)
    parser.add_argument("--cache-mb", type=int, default=None, help="default: the whole data set")
    parser.add_argument("--small-cache-fraction", type=float, default=0.5, help="0 skips ours_small_cache")
    parser.add_argument("--dir", default=None, help="folder for the files (default: a temporary one, removed)")
    parser.add_argument("--seed", type=int, default=0)
    add_record_argument(parser)
    args = parser.parse_args()
    folder = args.dir or tempfile.mkdtemp(prefix="bench-replay-")
    os.makedirs(folder, exist_ok=True)
    started = time.perf_counter()
    try:
        final = run(args, folder)
    finally:
        if args.dir is None:
            shutil.rmtree(folder, ignore_errors=True)
    final["elapsed_s"] = round(time.perf_counter() - started, 1)
    return conclude(final, record=(args.record, "Persistent replay buffer"))


def run(args, folder: str) -> dict:
    steps, n_obs, n_step = args.steps, args.episodes * (args.steps + 1), args.episodes * args.steps
    data_bytes = sum(SPEC.row_bytes(n) * (n_obs if n in SPEC.observations else n_step) for n in SPEC.fields)
    transition_bytes = 2 * sum(SPEC.row_bytes(n) for n in SPEC.observations) + sum(
        SPEC.row_bytes(n) for n in SPEC.steps)
    results: dict = {"data_mb": round(data_bytes / MIB, 1)}
    log = lambda name, res: print(f"[{name}] {json.dumps(res)}", file=sys.stderr, flush=True)  # noqa: E731

    # ---- append: ours, then the baseline's raw sequential write of the same rows
    store_dir = os.path.join(folder, "store")
    options = StoreOptions(segment_bytes=args.segment_mb * MIB, cache_bytes=0)
    rng, append_s = np.random.default_rng(args.seed), 0.0
    with ReplayStore(store_dir, SPEC, options=options) as store:
        for _ in range(args.episodes):
            episode = make_episode(rng, steps)
            start = time.perf_counter()
            store.append(episode)
            append_s += time.perf_counter() - start
    results["append_ours"] = {"episodes_per_s": round(args.episodes / append_s, 1),
                              "transitions_per_s": round(n_step / append_s),
                              "mb_per_s": round(data_bytes / append_s / MIB, 1), "durable": True}
    log("append_ours", results["append_ours"])
    os.makedirs(os.path.join(folder, "disk"), exist_ok=True)
    disk_paths, write_s = write_disk_files(os.path.join(folder, "disk"), args.episodes, steps, args.seed)
    results["append_disk_write"] = {"mb_per_s": round(data_bytes / write_s / MIB, 1)}
    log("append_disk_write", results["append_disk_write"])

    # ---- the same draws for everyone (the store's seeded sampler)
    cache_mb = args.cache_mb if args.cache_mb is not None else data_bytes // MIB + 64
    sampling = SamplingSpec(seed=args.seed)
    ours = ReplayStore(store_dir, writable=False, sampling=sampling,
                       options=StoreOptions(segment_bytes=args.segment_mb * MIB, cache_bytes=cache_mb * MIB))
    draws = [ours.sample_positions(args.batch) for _ in range(args.batches + 3)]
    warm, draws = draws[:3], draws[3:]

    def drop_ours(store=ours):
        store.release_maps()
        drop_pages(store.files())

    time_batches(ours.gather, warm)
    cached = sum(ours.segments[n].data_bytes for n in ours.cache.keys())
    results["ours"] = {**rates(time_batches(ours.gather, draws, drop_ours), len(draws), args.batch, transition_bytes),
                       "cache_mb": cache_mb, "cached_fraction": round(cached / data_bytes, 3),
                       "segments": len(ours.segments)}
    log("ours", results["ours"])

    disk = ArrayBuffer({}, steps)

    def drop_disk():
        disk.arrays = {}
        drop_pages(list(disk_paths.values()))
        disk.arrays = map_disk(disk_paths, n_obs, n_step)

    drop_disk()
    time_batches(disk.gather, warm)
    results["disk"] = rates(time_batches(disk.gather, draws, drop_disk), len(draws), args.batch, transition_bytes)
    log("disk", results["disk"])

    memory = ArrayBuffer({name: np.array(array) for name, array in map_disk(disk_paths, n_obs, n_step).items()}, steps)
    time_batches(memory.gather, warm)
    results["memory"] = rates(time_batches(memory.gather, draws), len(draws), args.batch, transition_bytes)
    log("memory", results["memory"])
    del memory
    ours.close()

    if args.small_cache_fraction > 0:
        small_mb = max(1, int(data_bytes * args.small_cache_fraction) // MIB)
        small = ReplayStore(store_dir, writable=False, sampling=sampling,
                            options=StoreOptions(segment_bytes=args.segment_mb * MIB, cache_bytes=small_mb * MIB))
        time_batches(small.gather, warm)
        cached = sum(small.segments[n].data_bytes for n in small.cache.keys())
        results["ours_small_cache"] = {
            **rates(time_batches(small.gather, draws, lambda: (small.release_maps(), drop_pages(small.files()))),
                    len(draws), args.batch, transition_bytes),
            "cache_mb": small_mb, "cached_fraction": round(cached / data_bytes, 3)}
        log("ours_small_cache", results["ours_small_cache"])
        small.close()

    ours_rate = results["ours"]["batches_per_s"]
    ratios = {"sample_vs_disk": round(ours_rate / results["disk"]["batches_per_s"], 3),
              "sample_vs_memory": round(ours_rate / results["memory"]["batches_per_s"], 3)}
    if "ours_small_cache" in results:
        ratios["small_cache_sample_vs_disk"] = round(
            results["ours_small_cache"]["batches_per_s"] / results["disk"]["batches_per_s"], 3)
    return {"benchmark": "replay_buffer", "ratios": ratios,
            "targets": {**TARGETS, "note": "sample_vs_memory = memory time / our time; >= 0.67 is within 1.5x"},
            "device": device_description(), "config": {k: v for k, v in vars(args).items() if k != "record"},
            "results": results}


if __name__ == "__main__":
    sys.exit(concluded("replay_buffer", main))
