"""Baseline (c): the original RLinf Channel (PyPI rlinf==0.3.0), measured in RLinf's own venv.

Run with the venv's python (benchmarks/setup_rlinf_venv.sh creates it); benchmarks/runtime_channel.py
does this for you:

    ~/.cache/infinirl/rlinf-venv/bin/python benchmarks/rlinf_channel_child.py [--quick] [--sizes 1KB,1MB]

Prints human-readable progress on stderr and ONE JSON line on stdout:
    {"impl": "rlinf", "sizes": {"1KB": {"items_per_s": .., "mb_per_s": .., "p50_ms": .., "p99_ms": ..,
     ...}, ...}, "versions": {...}}

Setup: `Cluster(num_nodes=1)` on a private Ray instance started by this process (never an existing
cluster: RLinf's `ray.init(address="auto")` is redirected to `address="local"`), one producer worker
group and one consumer worker group of one rank each (`NodePlacementStrategy([0])`), and per size a
data channel `Channel.create(name, maxsize=MAX_INFLIGHT[size])` plus an ack channel for ping pacing.
Producer and consumer call `channel.put(tensor)` / `channel.get()` from inside their workers, i.e.
RLinf's normal worker path: the payload goes producer -> ChannelWorker actor -> consumer, each hop a
gloo send/recv over loopback TCP (see the report in runtime_channel.py's docstring).

Methodology and sizes: benchmarks/_bench_common.py.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _bench_common as bc


def _force_private_ray() -> None:
    """RLinf's Cluster first tries `ray.init(address="auto")`, which would join any Ray cluster
    already running on the machine (another benchmark, another user). Redirect that to a fresh
    local instance owned by this process tree, without the dashboard (2-core machines)."""
    import ray

    orig_init = ray.init

    def init(*args, **kwargs):
        if kwargs.get("address") in (None, "auto"):
            kwargs["address"] = "local"
            kwargs.setdefault("include_dashboard", False)
            num_cpus = os.environ.get("INFINIRL_BENCH_RAY_CPUS")
            if num_cpus:
                kwargs.setdefault("num_cpus", int(num_cpus))
        return orig_init(*args, **kwargs)

    ray.init = init


def _define_workers():
    """Worker classes (defined lazily so that `--help` works without rlinf installed)."""
    from rlinf.scheduler import Worker

    def payload(nbytes: int):
        import torch

        t = torch.empty(nbytes, dtype=torch.uint8)
        t.fill_(0xA5)
        return t

    class BenchProducer(Worker):
        def __init__(self):
            super().__init__()

        def stream(self, channel, nbytes: int, n: int) -> float:
            """Put n items as fast as the channel takes them; returns the first put-start."""
            x = payload(nbytes)
            t_start = time.perf_counter()
            for _ in range(n):
                channel.put(x)
            return t_start

        def ping(self, channel, ack, nbytes: int, n: int) -> list[float]:
            """n puts, each waiting for the consumer's ack; returns each put-start."""
            x = payload(nbytes)
            starts = []
            for _ in range(n):
                t0 = time.perf_counter()
                channel.put(x)
                starts.append(t0)
                ack.get()
            return starts

    class BenchConsumer(Worker):
        def __init__(self):
            super().__init__()

        def drain(self, channel, nbytes: int, n: int) -> float:
            """Get n items; returns the last get-return."""
            t_end = 0.0
            for _ in range(n):
                x = channel.get()
                t_end = time.perf_counter()
                assert x.numel() == nbytes, (x.numel(), nbytes)
            return t_end

        def pong(self, channel, ack, nbytes: int, n: int) -> list[float]:
            """n gets, each acked; returns each get-return."""
            ends = []
            for i in range(n):
                x = channel.get()
                ends.append(time.perf_counter())
                assert x.numel() == nbytes, (x.numel(), nbytes)
                ack.put(i)
            return ends

    return BenchProducer, BenchConsumer


def run(sizes: list[str], quick: bool) -> dict:
    _force_private_ray()
    import importlib.metadata as md

    import ray
    import torch
    from rlinf.scheduler import Channel, Cluster, NodePlacementStrategy

    BenchProducer, BenchConsumer = _define_workers()
    t_setup = time.perf_counter()
    cluster = Cluster(num_nodes=1)
    producer = BenchProducer.create_group().launch(
        cluster, placement_strategy=NodePlacementStrategy([0]), name="bench_producer"
    )
    consumer = BenchConsumer.create_group().launch(
        cluster, placement_strategy=NodePlacementStrategy([0]), name="bench_consumer"
    )
    print(f"[rlinf] cluster + workers up in {time.perf_counter() - t_setup:.1f}s", file=sys.stderr)

    out: dict = {"impl": "rlinf", "sizes": {}}
    try:
        for label, p in bc.plan(sizes, quick).items():
            t_size = time.perf_counter()
            nbytes = p["nbytes"]
            data = Channel.create(f"bench_data_{label}", maxsize=p["max_inflight"])
            ack = Channel.create(f"bench_ack_{label}", maxsize=1)

            # warm-up: forms the gloo groups producer<->channel actor<->consumer, both ways
            for fn_p, fn_c in (("stream", "drain"), ("ping", "pong")):
                args = (data, ack) if fn_p == "ping" else (data,)
                hp = getattr(producer, fn_p)(*args, nbytes, p["warmup_n"])
                hc = getattr(consumer, fn_c)(*args, nbytes, p["warmup_n"])
                hp.wait(), hc.wait()

            # throughput
            hc = consumer.drain(data, nbytes, p["stream_n"])
            hp = producer.stream(data, nbytes, p["stream_n"])
            t_start = hp.wait()[0]
            t_end = hc.wait()[0]
            wall = t_end - t_start

            # latency
            hc = consumer.pong(data, ack, nbytes, p["ping_n"])
            hp = producer.ping(data, ack, nbytes, p["ping_n"])
            starts = hp.wait()[0]
            ends = hc.wait()[0]
            lat = [e - s for s, e in zip(starts, ends)]

            out["sizes"][label] = bc.size_result(nbytes, p["stream_n"], wall, lat)
            st = out["sizes"][label]
            print(
                f"[rlinf] {label}: {st['items_per_s']:.1f} items/s {st['mb_per_s']:.1f} MiB/s "
                f"p50 {st['p50_ms']:.3f} ms p99 {st['p99_ms']:.3f} ms "
                f"({time.perf_counter() - t_size:.1f}s)",
                file=sys.stderr,
            )
    finally:
        ray.shutdown()
    out["versions"] = {
        "rlinf": md.version("rlinf"),
        "ray": ray.__version__,
        "torch": torch.__version__,
    }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="short run (fewer items)")
    ap.add_argument("--sizes", default=None, help=f"comma list from {list(bc.SIZES)}")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = run(bc.parse_sizes(args.sizes), args.quick)
    out["elapsed_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
