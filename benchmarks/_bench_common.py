"""Shared helpers for the benchmarks: the channel benchmarks' methodology (benchmarks/runtime_channel.py
and benchmarks/rlinf_channel_child.py), and how every benchmark ends (:func:`conclude`).

Stdlib only at import time (torch is imported lazily), because this module is also imported by the
RLinf child script, which runs under a different virtualenv. Ray actors never import it: they only
need torch and time, so nothing here has to be importable inside worker processes.

Methodology, the same for every implementation:

* payload: a contiguous ``torch.uint8`` CPU tensor of 1 KiB, 1 MiB or 64 MiB ("1KB", "1MB", "64MB"),
  allocated once by the producer and sent again and again;
* latency ("ping"): one item in flight, the queue empty; the time from the producer's put-start to
  the moment the consumer's get returns the materialised tensor. Both ends are on one node and use
  ``time.perf_counter()`` (CLOCK_MONOTONIC on Linux, shared by all processes), so the two stamps
  compare directly. The producer waits for the consumer to acknowledge before the next put; that
  pacing is not timed. p50/p99 over many repeats, after warm-up;
* throughput ("stream"): N items as fast as possible, the consumer draining, at most
  ``MAX_INFLIGHT[size]`` items between producer and consumer (queue bound / back-pressure). Wall
  time = producer's first put-start to the consumer's last get-return.
  items/s = N / wall; MB/s = N * size / wall / 2**20 (MiB, like the size labels).
"""

from __future__ import annotations

import json
import math
import os
import platform
import statistics
import sys
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence

KIB = 1024
MIB = 1024 * 1024

#: label -> payload size in bytes
SIZES: dict[str, int] = {"1KB": KIB, "1MB": MIB, "64MB": 64 * MIB}

#: items streamed for the throughput measurement
STREAM_N: dict[str, int] = {"1KB": 2000, "1MB": 500, "64MB": 20}
QUICK_STREAM_N: dict[str, int] = {"1KB": 300, "1MB": 60, "64MB": 6}

#: ping repeats for the latency measurement
PING_N: dict[str, int] = {"1KB": 300, "1MB": 100, "64MB": 10}
QUICK_PING_N: dict[str, int] = {"1KB": 60, "1MB": 20, "64MB": 4}

#: untimed warm-up items (stream and ping each) before every measurement
WARMUP_N: dict[str, int] = {"1KB": 20, "1MB": 5, "64MB": 2}

#: bound on items in flight between producer and consumer (queue maxsize / outstanding calls).
#: 64 MiB x 4 keeps the worst case at a few hundred MiB per copy the transport holds.
MAX_INFLIGHT: dict[str, int] = {"1KB": 64, "1MB": 16, "64MB": 4}

#: what `runtime_channel.py` reports: higher is better for InfiniRL in every ratio
TARGETS: dict[str, float] = {
    "throughput_1MB_vs_ray": 0.8,
    "throughput_64MB_vs_ray": 0.8,
    "throughput_1MB_vs_rlinf": 2.0,
    "latency_1KB_vs_ray_call": 0.5,
}


def parse_sizes(spec: str | None) -> list[str]:
    """`"1KB,64MB"` -> `["1KB", "64MB"]` (validated, in SIZES order); None/"" -> all sizes."""
    if not spec:
        return list(SIZES)
    wanted = [s.strip().upper() for s in spec.split(",") if s.strip()]
    unknown = [s for s in wanted if s not in SIZES]
    if unknown:
        raise ValueError(f"unknown size(s) {unknown}; choose from {list(SIZES)}")
    return [s for s in SIZES if s in wanted]


def plan(sizes: Sequence[str], quick: bool = False) -> dict[str, dict[str, int]]:
    """Per-size parameters: {label: {nbytes, stream_n, ping_n, warmup_n, max_inflight}}."""
    stream = QUICK_STREAM_N if quick else STREAM_N
    ping = QUICK_PING_N if quick else PING_N
    return {
        s: {
            "nbytes": SIZES[s],
            "stream_n": stream[s],
            "ping_n": ping[s],
            "warmup_n": WARMUP_N[s],
            "max_inflight": MAX_INFLIGHT[s],
        }
        for s in sizes
    }


def percentile(values: Sequence[float], q: float) -> float:
    """Linear-interpolated percentile (numpy's default method), q in [0, 100]."""
    if not values:
        return math.nan
    xs = sorted(values)
    if len(xs) == 1:
        return float(xs[0])
    pos = (len(xs) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(xs) - 1)
    return float(xs[lo] + (xs[hi] - xs[lo]) * (pos - lo))


def latency_stats(latencies_s: Iterable[float]) -> dict[str, float]:
    """Seconds -> {p50_ms, p99_ms, mean_ms, n}."""
    xs = [float(x) for x in latencies_s]
    return {
        "p50_ms": percentile(xs, 50) * 1e3,
        "p99_ms": percentile(xs, 99) * 1e3,
        "mean_ms": (statistics.fmean(xs) * 1e3) if xs else math.nan,
        "ping_n": len(xs),
    }


def throughput_stats(nbytes: int, n_items: int, wall_s: float) -> dict[str, float]:
    """-> {items_per_s, mb_per_s (MiB/s), stream_n, stream_wall_s}."""
    if wall_s <= 0:
        return {
            "items_per_s": math.nan,
            "mb_per_s": math.nan,
            "stream_n": n_items,
            "stream_wall_s": wall_s,
        }
    return {
        "items_per_s": n_items / wall_s,
        "mb_per_s": n_items * nbytes / wall_s / MIB,
        "stream_n": n_items,
        "stream_wall_s": wall_s,
    }


def size_result(
    nbytes: int, n_items: int, wall_s: float, latencies_s: Iterable[float]
) -> dict[str, float]:
    """One size's entry: throughput_stats | latency_stats, rounded for printing."""
    out = {**throughput_stats(nbytes, n_items, wall_s), **latency_stats(latencies_s)}
    return {
        k: (round(v, 4) if isinstance(v, float) and math.isfinite(v) else v) for k, v in out.items()
    }


def make_payload(nbytes: int):
    """A contiguous uint8 CPU tensor of nbytes, filled (so its pages are really allocated)."""
    import torch

    t = torch.empty(nbytes, dtype=torch.uint8)
    t.fill_(0xA5)
    return t


def device_description() -> str:
    """CPU model (and GPU name if torch sees one), for the result line."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    desc = f"{cpu} ({os.cpu_count()} cpus)"
    try:
        import torch

        if torch.cuda.is_available():
            desc += f"; GPU {torch.cuda.get_device_name(0)}"
    except Exception as e:  # noqa: BLE001 - torch missing or CUDA broken: CPU description only
        desc += f"; GPU query failed: {type(e).__name__}"
    return desc


def format_table(results: Mapping[str, Mapping]) -> str:
    """{impl: {"sizes": {label: stats}}} -> a fixed-width text table."""
    header = (
        f"{'impl':<10}{'size':>6}{'items/s':>12}{'MiB/s':>11}"
        f"{'p50 ms':>10}{'p99 ms':>10}{'stream n':>10}{'ping n':>8}"
    )
    lines = [header, "-" * len(header)]
    for impl, res in results.items():
        if not res or "sizes" not in res:
            res = res or {}
            why = f"failed: {res['failed']}" if res.get("failed") else f"skipped: {res.get('skipped', 'no result')}"
            lines.append(f"{impl:<10}  {why}")
            continue
        for label, st in res["sizes"].items():
            lines.append(
                f"{impl:<10}{label:>6}{st.get('items_per_s', math.nan):>12.1f}"
                f"{st.get('mb_per_s', math.nan):>11.1f}{st.get('p50_ms', math.nan):>10.3f}"
                f"{st.get('p99_ms', math.nan):>10.3f}{st.get('stream_n', 0):>10}"
                f"{st.get('ping_n', 0):>8}"
            )
    return "\n".join(lines)


def find_json_line(text: str, required_key: str) -> dict | None:
    """The last line of `text` that parses as a JSON object holding `required_key`."""
    for line in reversed(text.splitlines()):
        line = line.strip()
        if not (line.startswith("{") and line.endswith("}")):
            continue
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        if isinstance(obj, dict) and required_key in obj:
            return obj
    return None


def add_record_argument(parser) -> None:
    parser.add_argument("--record", metavar="RESULTS_MD", default=None,
                        help="append this run's final JSON line, command and host to a results file "
                             "(docs/results.md) as a new entry")


def record_result(path: str | None, title: str, final: Mapping) -> None:
    """With ``--record``: the final JSON line as a results entry (command, host probe, today's
    date, as the benchmark ends, and the commit of the code, ``-dirty`` with uncommitted changes)."""
    if not path:
        return
    import shlex
    import sys

    from infinirl.results import append_entry, code_version, format_entry, host_probe

    command = shlex.join(["python", *sys.argv])
    append_entry(path, format_entry(title=title, command=command, result=dict(final),
                                    host={**host_probe(), **dict(final.get("host") or {})}, commit=code_version()))


# --------------------------------------------------------------------------------------------
# How a benchmark ends: one final JSON line, always, and an exit status that says whether it holds
# --------------------------------------------------------------------------------------------
def side_failed(reason: str) -> dict:
    """A side's (row's, impl's) entry in ``results`` when it could not be measured."""
    return {"failed": reason}


def failures_of(results: Mapping[str, object], prefix: str = "") -> list[str]:
    """``"<name>: <reason>"`` for every entry of ``results`` that holds ``failed`` (skipped sides,
    e.g. an optional baseline that is not installed, are not failures)."""
    return [f"{prefix}{name}: {entry['failed']}" for name, entry in results.items()
            if isinstance(entry, Mapping) and entry.get("failed")]


def conclude(final: Mapping, failures: Iterable[str] = (), record: tuple[str | None, str] | None = None) -> int:
    """Print ``final`` as the last stdout line, with ``"failures"`` (a required side that failed, a
    same-work check that did not hold), and return the exit status: 1 with any failure, else 0.
    ``record``: (``--record``'s path or None, the entry's title); a failed run is not recorded."""
    failures = list(failures)
    final = {**final, "failures": failures}
    for failure in failures:
        print(f"{final.get('benchmark', 'benchmark')}: FAILED: {failure}", file=sys.stderr, flush=True)
    if record is not None and record[0]:
        if failures:
            print(f"not recorded in {record[0]}: the run failed", file=sys.stderr, flush=True)
        else:
            record_result(record[0], record[1], final)
    print(json.dumps(final), flush=True)
    return 1 if failures else 0


def concluded(benchmark: str, main: Callable[[], int | None]) -> int:
    """``main()``'s exit status; an exception it did not turn into a failed side still ends the run
    with a final JSON line naming it, and exit 1 (argument errors, ``SystemExit``, pass through)."""
    try:
        return main() or 0
    except Exception as error:  # noqa: BLE001 - any crash: the traceback to stderr, the failure to the JSON line
        traceback.print_exc()
        return conclude({"benchmark": benchmark, "ratios": {}}, [f"{type(error).__name__}: {error}"])
