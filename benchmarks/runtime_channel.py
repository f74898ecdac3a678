"""Benchmark: InfiniRL `infinirl.runtime.Channel` vs raw Ray vs the original RLinf Channel.

Between two workers (Ray actors) on one node, for torch.uint8 payloads of 1 KiB, 1 MiB and 64 MiB,
it measures throughput (items/s, MiB/s) and p50/p99 one-way latency of

  (a) infinirl: our Channel                               -> bench_infinirl_channel() (lead: TODO)
  (b) ray:      a producer actor `ray.put`s the tensor and passes the ObjectRef to a consumer actor
                method, which receives it materialised (Ray resolves top-level ObjectRef arguments)
  (c) rlinf:    RLinf 0.3.0's Channel in its own virtualenv (benchmarks/rlinf_channel_child.py;
                create the venv with `bash benchmarks/setup_rlinf_venv.sh`)

Methodology (same for all three): see benchmarks/_bench_common.py. Every implementation runs in its
own subprocess with its own private Ray instance (`ray.init(address="local")`), one after the other,
so none of them sees another's actors, memory or CPU load.

Usage:
    python benchmarks/runtime_channel.py                 # all impls, all sizes (~2-4 min on 2 cores)
    python benchmarks/runtime_channel.py --quick         # short run
    python benchmarks/runtime_channel.py --sizes 1KB,1MB --impls ray,rlinf
    python benchmarks/runtime_channel.py --only ray      # one impl in-process, prints its JSON line

The human-readable table goes to stderr; the last line on stdout is ONE JSON object:
    {"benchmark": "runtime_channel", "ratios": {...}, "targets": {...}, "device": "...",
     "results": {impl: {"sizes": {...}} | {"skipped": reason}}, "elapsed_s": ...}
Every ratio > 1 means InfiniRL is better: throughput = ours / theirs (MiB/s), latency = raw Ray p50 /
our p50. A ratio is null when either side did not run.

Environment:
    INFINIRL_RLINF_VENV       RLinf venv (default ~/.cache/infinirl/rlinf-venv)
    INFINIRL_BENCH_RAY_CPUS   num_cpus for every private Ray instance (default: Ray's detection)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import deque

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import _bench_common as bc  # noqa: E402

IMPLS = ("infinirl", "ray", "rlinf")
RLINF_VENV_DEFAULT = os.path.join(os.path.expanduser("~"), ".cache", "infinirl", "rlinf-venv")
SUBPROCESS_TIMEOUT_S = {False: 1800, True: 600}  # full / --quick


def _ray_init():
    """A private local Ray instance for this process tree (never joins an existing cluster)."""
    import ray

    kwargs = {"address": "local", "include_dashboard": False, "log_to_driver": True}
    if os.environ.get("INFINIRL_BENCH_RAY_CPUS"):
        kwargs["num_cpus"] = int(os.environ["INFINIRL_BENCH_RAY_CPUS"])
    ray.init(**kwargs)
    return ray


# --------------------------------------------------------------------------------------------
# (a) InfiniRL Channel  -- TO BE FILLED IN BY THE LEAD
# --------------------------------------------------------------------------------------------
def bench_infinirl_channel(plan: dict[str, dict[str, int]]) -> dict:
    """Measure `infinirl.runtime.Channel` between two workers on one node.

    Args:
        plan: `_bench_common.plan(sizes, quick)`: {label: {"nbytes", "stream_n", "ping_n",
            "warmup_n", "max_inflight"}}.

    Returns:
        {"impl": "infinirl", "sizes": {label: bc.size_result(nbytes, stream_n, wall_s, lat_s)}}

    Intended shape (mirror bench_ray_baseline / rlinf_channel_child.py exactly):
        1. start InfiniRL's Cluster on a private Ray instance (e.g. `_ray_init()` first, or the
           Cluster's own local start) and launch a producer and a consumer Worker (one rank each);
        2. per size: `ch = Channel(name, maxsize=p["max_inflight"])` (+ a small ack channel);
           warm-up `p["warmup_n"]` items through both the stream and the ping loop;
        3. throughput: consumer `for _ in range(n): x = ch.get(); t_end = perf_counter()`,
           producer `t_start = perf_counter(); for _ in range(n): ch.put(x)` with
           x = bc-style payload (uint8, filled, allocated once); wall = t_end - t_start;
        4. latency: producer `t0 = perf_counter(); ch.put(x); ack.get()`, consumer
           `x = ch.get(); t1 = perf_counter(); ack.put(i)`; lat = t1 - t0 per item;
        5. shut Ray down in a `finally`.
    """
    raise NotImplementedError(
        "bench_infinirl_channel: fill in once infinirl.runtime.Channel exists (see docstring)")


# --------------------------------------------------------------------------------------------
# (b) raw Ray baseline
# --------------------------------------------------------------------------------------------
def _define_ray_actors(ray):
    import torch  # noqa: F401

    @ray.remote
    class RayConsumer:
        def consume(self, x, nbytes: int) -> float:
            # `x` arrives materialised: Ray resolved the ObjectRef argument before the call.
            t = time.perf_counter()
            assert x.numel() == nbytes, (x.numel(), nbytes)
            return t

    @ray.remote
    class RayProducer:
        def __init__(self, consumer):
            self.consumer = consumer

        @staticmethod
        def _payload(nbytes: int):
            import torch

            t = torch.empty(nbytes, dtype=torch.uint8)
            t.fill_(0xA5)
            return t

        def stream(self, nbytes: int, n: int, max_inflight: int) -> float:
            """n items, at most max_inflight outstanding; returns wall (first put-start to the
            consumer's last materialisation)."""
            x = self._payload(nbytes)
            inflight: deque = deque()
            t_start = time.perf_counter()
            for _ in range(n):
                if len(inflight) >= max_inflight:
                    ray.get(inflight.popleft())
                inflight.append(self.consumer.consume.remote(ray.put(x), nbytes))
            t_end = ray.get(list(inflight))[-1]
            return t_end - t_start

        def ping(self, nbytes: int, n: int) -> list[float]:
            """n single items, each awaited; returns put-start -> consumer-materialised."""
            x = self._payload(nbytes)
            lat = []
            for _ in range(n):
                t0 = time.perf_counter()
                t1 = ray.get(self.consumer.consume.remote(ray.put(x), nbytes))
                lat.append(t1 - t0)
            return lat

    return RayProducer, RayConsumer


def bench_ray_baseline(plan: dict[str, dict[str, int]]) -> dict:
    ray = _ray_init()
    out: dict = {"impl": "ray", "sizes": {}}
    try:
        RayProducer, RayConsumer = _define_ray_actors(ray)
        consumer = RayConsumer.remote()
        producer = RayProducer.remote(consumer)
        for label, p in plan.items():
            t_size = time.perf_counter()
            nbytes = p["nbytes"]
            ray.get(producer.stream.remote(nbytes, p["warmup_n"], p["max_inflight"]))
            ray.get(producer.ping.remote(nbytes, p["warmup_n"]))
            wall = ray.get(producer.stream.remote(nbytes, p["stream_n"], p["max_inflight"]))
            lat = ray.get(producer.ping.remote(nbytes, p["ping_n"]))
            out["sizes"][label] = st = bc.size_result(nbytes, p["stream_n"], wall, lat)
            print(f"[ray] {label}: {st['items_per_s']:.1f} items/s {st['mb_per_s']:.1f} MiB/s "
                  f"p50 {st['p50_ms']:.3f} ms p99 {st['p99_ms']:.3f} ms "
                  f"({time.perf_counter() - t_size:.1f}s)", file=sys.stderr)
        out["versions"] = {"ray": ray.__version__, "torch": __import__("torch").__version__}
    finally:
        ray.shutdown()
    return out


# --------------------------------------------------------------------------------------------
# (c) RLinf, in its own venv
# --------------------------------------------------------------------------------------------
def rlinf_python() -> str | None:
    venv = os.environ.get("INFINIRL_RLINF_VENV", RLINF_VENV_DEFAULT)
    py = os.path.join(venv, "bin", "python")
    return py if os.access(py, os.X_OK) else None


def _run_subprocess(cmd: list[str], label: str, timeout_s: int, key: str = "impl") -> dict:
    print(f"[driver] {label}: {' '.join(cmd)}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=None, text=True,
                              timeout=timeout_s, cwd=os.path.dirname(HERE))
    except subprocess.TimeoutExpired:
        return {"skipped": f"timed out after {timeout_s}s"}
    res = bc.find_json_line(proc.stdout, key)
    elapsed = time.perf_counter() - t0
    print(f"[driver] {label}: exit {proc.returncode} after {elapsed:.1f}s", file=sys.stderr)
    if proc.returncode != 0 or res is None:
        tail = "\n".join(proc.stdout.splitlines()[-20:])
        return {"skipped": f"{label} failed (exit {proc.returncode}); stdout tail:\n{tail}"}
    res.setdefault("elapsed_s", round(elapsed, 1))
    return res


def run_rlinf(sizes: list[str], quick: bool) -> dict:
    py = rlinf_python()
    if py is None:
        venv = os.environ.get("INFINIRL_RLINF_VENV", RLINF_VENV_DEFAULT)
        msg = (f"RLinf venv not found at {venv}; create it with "
               f"`bash benchmarks/setup_rlinf_venv.sh` (or set INFINIRL_RLINF_VENV)")
        print(f"[driver] rlinf skipped: {msg}", file=sys.stderr)
        return {"skipped": msg}
    cmd = [py, os.path.join(HERE, "rlinf_channel_child.py"), "--sizes", ",".join(sizes)]
    if quick:
        cmd.append("--quick")
    return _run_subprocess(cmd, "rlinf", SUBPROCESS_TIMEOUT_S[quick])


# --------------------------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------------------------
def _ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None or not den:
        return None
    return round(num / den, 4)


def _stat(results: dict, impl: str, size: str, key: str) -> float | None:
    try:
        return results[impl]["sizes"][size][key]
    except (KeyError, TypeError):
        return None


def compute_ratios(results: dict) -> dict:
    ours = "infinirl"
    return {
        "throughput_1MB_vs_ray": _ratio(_stat(results, ours, "1MB", "mb_per_s"),
                                        _stat(results, "ray", "1MB", "mb_per_s")),
        "throughput_64MB_vs_ray": _ratio(_stat(results, ours, "64MB", "mb_per_s"),
                                         _stat(results, "ray", "64MB", "mb_per_s")),
        "throughput_1MB_vs_rlinf": _ratio(_stat(results, ours, "1MB", "mb_per_s"),
                                          _stat(results, "rlinf", "1MB", "mb_per_s")),
        "latency_1KB_vs_ray_call": _ratio(_stat(results, "ray", "1KB", "p50_ms"),
                                          _stat(results, ours, "1KB", "p50_ms")),
    }


def run_one_inprocess(impl: str, sizes: list[str], quick: bool) -> dict:
    p = bc.plan(sizes, quick)
    t0 = time.perf_counter()
    if impl == "ray":
        out = bench_ray_baseline(p)
    elif impl == "infinirl":
        out = bench_infinirl_channel(p)
    else:
        raise ValueError(f"--only {impl}: rlinf runs in its own venv (rlinf_channel_child.py)")
    out["elapsed_s"] = round(time.perf_counter() - t0, 1)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="short run (fewer items)")
    ap.add_argument("--sizes", default=None, help=f"comma list from {list(bc.SIZES)} (default all)")
    ap.add_argument("--impls", default=",".join(IMPLS), help=f"comma list from {list(IMPLS)}")
    ap.add_argument("--only", choices=("infinirl", "ray"),
                    help="run one impl in this process and print its JSON line (used by the driver)")
    args = ap.parse_args(argv)
    sizes = bc.parse_sizes(args.sizes)

    if args.only:
        try:
            out = run_one_inprocess(args.only, sizes, args.quick)
        except NotImplementedError as e:
            out = {"impl": args.only, "skipped": f"not implemented yet: {e}"}
        print(json.dumps(out), flush=True)
        return 0

    impls = [i.strip() for i in args.impls.split(",") if i.strip()]
    bad = [i for i in impls if i not in IMPLS]
    if bad:
        ap.error(f"unknown impl(s) {bad}; choose from {list(IMPLS)}")

    t0 = time.perf_counter()
    results: dict = {}
    for impl in IMPLS:
        if impl not in impls:
            continue
        if impl == "rlinf":
            results[impl] = run_rlinf(sizes, args.quick)
            continue
        cmd = [sys.executable, os.path.abspath(__file__), "--only", impl, "--sizes", ",".join(sizes)]
        if args.quick:
            cmd.append("--quick")
        results[impl] = _run_subprocess(cmd, impl, SUBPROCESS_TIMEOUT_S[args.quick])

    print(bc.format_table(results), file=sys.stderr)
    line = {
        "benchmark": "runtime_channel",
        "ratios": compute_ratios(results),
        "targets": dict(bc.TARGETS),
        "device": bc.device_description(),
        "quick": args.quick,
        "results": results,
        "elapsed_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
