"""Benchmark: InfiniRL `infinirl.runtime.Channel` vs raw Ray vs the original RLinf Channel.

Between two workers (Ray actors) on one node, for torch.uint8 payloads of 1 KiB, 1 MiB and 64 MiB,
it measures throughput (items/s, MiB/s) and p50/p99 one-way latency of

  (a) infinirl: our Channel (producer Worker -> Channel -> consumer Worker)
  (b) ray:      a producer actor `ray.put`s the tensor and passes the ObjectRef to a consumer actor
                method, which receives it materialised (Ray resolves top-level ObjectRef arguments)
  (c) rlinf:    RLinf 0.3.0's Channel in its own virtualenv (benchmarks/rlinf_channel_child.py;
                create the venv with `bash benchmarks/setup_rlinf_venv.sh`)
  (info) ray_numpy: like (b) but puts the tensor's numpy view, which Ray returns zero-copy; opt-in
                in the default run; reported as the informational ratios *_vs_ray_numpy

Methodology (same for all three): see benchmarks/_bench_common.py. Every implementation runs in its
own subprocess with its own private Ray instance (`ray.init(address="local")`), one after the other,
so none of them sees another's actors, memory or CPU load.

Usage:
    python benchmarks/runtime_channel.py                 # all impls, all sizes (minutes)
    python benchmarks/runtime_channel.py --quick         # short run
    python benchmarks/runtime_channel.py --sizes 1KB,1MB --impls ray,rlinf
    python benchmarks/runtime_channel.py --only ray      # one impl in-process, prints its JSON line

The human-readable table goes to stderr; the last line on stdout is ONE JSON object:
    {"benchmark": "runtime_channel", "ratios": {...}, "targets": {...}, "device": "...",
     "results": {impl: {"sizes": {...}} | {"skipped": reason} | {"failed": reason}}, "elapsed_s": ...,
     "failures": [...]}
Every ratio > 1 means InfiniRL is better: throughput = ours / theirs (MiB/s), latency = raw Ray p50 /
our p50. A ratio is null when either side did not run. An impl that was asked for and failed (or
timed out) holds "failed" and the script exits 1; RLinf without its venv is skipped, not failed.

Environment:
    INFINIRL_RLINF_VENV       RLinf venv (default ~/.cache/infinirl/rlinf-venv)
    INFINIRL_BENCH_RAY_CPUS   num_cpus for every private Ray instance (default: Ray's detection)
    RAY_ENABLE_ZERO_COPY_TORCH_TENSORS  Ray's opt-in zero-copy torch serialiser; unset by default,
                              which makes (b) pickle the tensor storage and copy it again on get
                              (~5-8x slower at 1MB/64MB than with it or than `ray_numpy`). Its value
                              is recorded in the ray result.

What RLinf 0.3.0 does (c): inside a Worker, `channel.put(x)` enqueues a gloo send of x to the
ChannelWorker actor (object type, pickled metadata, then the tensor bytes, over loopback TCP) and
calls `channel_actor.put.remote(src_addr)`, which `recv`s it into a fresh tensor and queues it;
`channel.get()` calls `channel_actor.get.remote(dst_addr, query_id)`, which gloo-sends the queued
tensor on to the consumer, which `recv`s it into another fresh tensor. So every payload crosses
two TCP hops through the channel actor: 4 full copies (user->kernel->user per hop), a full copy
held by the channel actor per queued item, 3 small gloo messages per hop before the payload, and
one Ray actor call per put and per get.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import deque

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _bench_common as bc

HERE = os.path.dirname(os.path.abspath(__file__))
IMPLS = ("infinirl", "ray", "rlinf", "ray_numpy")
DEFAULT_IMPLS = ("infinirl", "ray", "rlinf", "ray_numpy")  # ray_numpy: informational, a stronger baseline
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
# (a) InfiniRL Channel
# --------------------------------------------------------------------------------------------
def _define_channel_workers():
    """The producer and consumer Worker classes of (a), defined where torch is imported."""
    import torch

    from infinirl.runtime import Worker

    class ChannelProducer(Worker):
        def _payload(self, nbytes):
            x = torch.empty(nbytes, dtype=torch.uint8)
            x.fill_(0xA5)
            return x

        def stream(self, ch, nbytes, n):
            x = self._payload(nbytes)
            t_start = time.perf_counter()
            for _ in range(n):
                ch.put(x)
            ch.flush()
            return t_start

        def ping(self, ch, ack, nbytes, n):
            x = self._payload(nbytes)
            starts = []
            for _ in range(n):
                starts.append(time.perf_counter())
                ch.put(x)
                ch.flush()
                ack.get()
            return starts

    class ChannelConsumer(Worker):
        def stream(self, ch, nbytes, n):
            for _ in range(n):
                x = ch.get()
                assert x.numel() == nbytes
            return time.perf_counter()

        def ping(self, ch, ack, nbytes, n):
            ends = []
            for i in range(n):
                x = ch.get()
                ends.append(time.perf_counter())
                assert x.numel() == nbytes
                ack.put(i)
            return ends

    return ChannelProducer, ChannelConsumer


def _bench_channel_size(producer, consumer, label: str, p: dict[str, int]) -> dict:
    """(a) at one payload size: a fresh data Channel and ack Channel, warm-up, then the measured
    stream and ping; prints the size's line and returns its result."""
    from infinirl.runtime import Channel

    t_size = time.perf_counter()
    nbytes = p["nbytes"]
    # A streaming producer keeps puts in flight and the consumer prefetches, like (b) keeps
    # calls in flight; queue + in-flight puts + prefetched items together stay within the
    # same bound (max_inflight) as (b).
    depth = max(1, p["max_inflight"] // 4)
    ch = Channel.create(f"bench-{label}", maxsize=p["max_inflight"] - 2 * depth,
                        pipeline_depth=depth, prefetch=depth)
    ack = Channel.create(f"bench-{label}-ack", maxsize=1)

    def stream(n):
        got = consumer.stream(ch, nbytes, n)
        t_start = producer.stream(ch, nbytes, n).wait()[0]
        return got.wait()[0] - t_start

    def ping(n):
        ends = consumer.ping(ch, ack, nbytes, n)
        starts = producer.ping(ch, ack, nbytes, n).wait()[0]
        return [e - s for s, e in zip(starts, ends.wait()[0])]

    stream(p["warmup_n"])
    ping(p["warmup_n"])
    wall = stream(p["stream_n"])
    lat = ping(p["ping_n"])
    st = bc.size_result(nbytes, p["stream_n"], wall, lat)
    print(
        f"[infinirl] {label}: {st['items_per_s']:.1f} items/s {st['mb_per_s']:.1f} MiB/s "
        f"p50 {st['p50_ms']:.3f} ms p99 {st['p99_ms']:.3f} ms "
        f"({time.perf_counter() - t_size:.1f}s)",
        file=sys.stderr,
    )
    ch.destroy()
    ack.destroy()
    return st


def bench_infinirl_channel(plan: dict[str, dict[str, int]]) -> dict:
    """(a): a producer Worker and a consumer Worker (one rank each) joined by an InfiniRL Channel.

    Same methodology as (b): throughput streams n items with at most ``max_inflight`` queued
    (the channel's ``maxsize`` gives the back-pressure), latency is put-start -> get-return with
    one item in flight, paced by an untimed ack channel.
    """
    import ray
    import torch

    from infinirl.runtime import Cluster, WorkerGroup

    ChannelProducer, ChannelConsumer = _define_channel_workers()
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    cluster_kwargs = {"log_to_driver": True}
    if os.environ.get("INFINIRL_BENCH_RAY_CPUS"):
        cluster_kwargs["num_cpus"] = int(os.environ["INFINIRL_BENCH_RAY_CPUS"])
    cluster = Cluster(**cluster_kwargs).start()
    out: dict = {"impl": "infinirl", "sizes": {}}
    try:
        producer = WorkerGroup.launch(ChannelProducer, "producer", num_ranks=1)
        consumer = WorkerGroup.launch(ChannelConsumer, "consumer", num_ranks=1)
        for label, p in plan.items():
            out["sizes"][label] = _bench_channel_size(producer, consumer, label, p)
        out["versions"] = {"ray": ray.__version__, "torch": torch.__version__}
    finally:
        cluster.shutdown()
    return out


# --------------------------------------------------------------------------------------------
# (b) raw Ray baseline
# --------------------------------------------------------------------------------------------
def _define_ray_actors(ray):
    import torch

    @ray.remote
    class RayConsumer:
        def __init__(self):
            import warnings

            # torch.from_numpy on Ray's read-only zero-copy buffer warns once; harmless here.
            warnings.filterwarnings("ignore", message="The given NumPy array is not writable")

        def consume(self, x, nbytes: int) -> float:
            # `x` arrives materialised: Ray resolved the ObjectRef argument before the call.
            if not isinstance(x, torch.Tensor):  # ray_numpy variant: zero-copy view of plasma
                x = torch.from_numpy(x)
            t = time.perf_counter()
            assert x.numel() == nbytes, (x.numel(), nbytes)
            return t

    @ray.remote
    class RayProducer:
        def __init__(self, consumer, as_numpy: bool = False):
            self.consumer = consumer
            self.as_numpy = as_numpy

        def _payload(self, nbytes: int):
            t = torch.empty(nbytes, dtype=torch.uint8)
            t.fill_(0xA5)
            # ray_numpy: put the tensor's numpy view (same memory), which Ray stores as a
            # pickle-5 out-of-band buffer and hands back zero-copy; a torch tensor is pickled
            # through its storage and copied again on deserialisation.
            return t.numpy() if self.as_numpy else t

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


def bench_ray_baseline(plan: dict[str, dict[str, int]], as_numpy: bool = False) -> dict:
    """(b): torch tensor through ray.put / ObjectRef argument. as_numpy=True is the informational
    `ray_numpy` variant (numpy view of the same tensor, zero-copy on the consumer side)."""
    ray = _ray_init()
    impl = "ray_numpy" if as_numpy else "ray"
    out: dict = {"impl": impl, "sizes": {}}
    try:
        RayProducer, RayConsumer = _define_ray_actors(ray)
        consumer = RayConsumer.remote()
        producer = RayProducer.remote(consumer, as_numpy)
        for label, p in plan.items():
            t_size = time.perf_counter()
            nbytes = p["nbytes"]
            ray.get(producer.stream.remote(nbytes, p["warmup_n"], p["max_inflight"]))
            ray.get(producer.ping.remote(nbytes, p["warmup_n"]))
            wall = ray.get(producer.stream.remote(nbytes, p["stream_n"], p["max_inflight"]))
            lat = ray.get(producer.ping.remote(nbytes, p["ping_n"]))
            out["sizes"][label] = st = bc.size_result(nbytes, p["stream_n"], wall, lat)
            print(
                f"[{impl}] {label}: {st['items_per_s']:.1f} items/s {st['mb_per_s']:.1f} MiB/s "
                f"p50 {st['p50_ms']:.3f} ms p99 {st['p99_ms']:.3f} ms "
                f"({time.perf_counter() - t_size:.1f}s)",
                file=sys.stderr,
            )
        out["versions"] = {"ray": ray.__version__, "torch": __import__("torch").__version__}
        # Ray's opt-in zero-copy torch serialiser changes (b) ~5x at 1MB/64MB: record it.
        out["RAY_ENABLE_ZERO_COPY_TORCH_TENSORS"] = os.environ.get(
            "RAY_ENABLE_ZERO_COPY_TORCH_TENSORS", "unset"
        )
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
        proc = subprocess.run(
            cmd,
            check=False,
            stdout=subprocess.PIPE,
            stderr=None,
            text=True,
            timeout=timeout_s,
            cwd=os.path.dirname(HERE),
        )
    except subprocess.TimeoutExpired:
        return bc.side_failed(f"timed out after {timeout_s}s")
    res = bc.find_json_line(proc.stdout, key)
    elapsed = time.perf_counter() - t0
    print(f"[driver] {label}: exit {proc.returncode} after {elapsed:.1f}s", file=sys.stderr)
    if proc.returncode != 0 or res is None:
        tail = "\n".join(proc.stdout.splitlines()[-20:])
        return bc.side_failed(f"{label} failed (exit {proc.returncode}); stdout tail:\n{tail}")
    res.setdefault("elapsed_s", round(elapsed, 1))
    return res


def run_rlinf(sizes: list[str], quick: bool) -> dict:
    py = rlinf_python()
    if py is None:
        venv = os.environ.get("INFINIRL_RLINF_VENV", RLINF_VENV_DEFAULT)
        msg = (
            f"RLinf venv not found at {venv}; create it with "
            f"`bash benchmarks/setup_rlinf_venv.sh` (or set INFINIRL_RLINF_VENV)"
        )
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
        "throughput_1MB_vs_ray": _ratio(
            _stat(results, ours, "1MB", "mb_per_s"), _stat(results, "ray", "1MB", "mb_per_s")
        ),
        "throughput_64MB_vs_ray": _ratio(
            _stat(results, ours, "64MB", "mb_per_s"), _stat(results, "ray", "64MB", "mb_per_s")
        ),
        "throughput_1MB_vs_rlinf": _ratio(
            _stat(results, ours, "1MB", "mb_per_s"), _stat(results, "rlinf", "1MB", "mb_per_s")
        ),
        "latency_1KB_vs_ray_call": _ratio(
            _stat(results, "ray", "1KB", "p50_ms"), _stat(results, ours, "1KB", "p50_ms")
        ),
        # Not a target: raw Ray given numpy views (zero-copy), the strongest hand-written baseline.
        "throughput_1MB_vs_ray_numpy": _ratio(
            _stat(results, ours, "1MB", "mb_per_s"), _stat(results, "ray_numpy", "1MB", "mb_per_s")
        ),
        "throughput_64MB_vs_ray_numpy": _ratio(
            _stat(results, ours, "64MB", "mb_per_s"), _stat(results, "ray_numpy", "64MB", "mb_per_s")
        ),
    }


def run_one_inprocess(impl: str, sizes: list[str], quick: bool) -> dict:
    p = bc.plan(sizes, quick)
    t0 = time.perf_counter()
    if impl == "ray":
        out = bench_ray_baseline(p)
    elif impl == "ray_numpy":
        out = bench_ray_baseline(p, as_numpy=True)
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
    ap.add_argument(
        "--impls",
        default=",".join(DEFAULT_IMPLS),
        help=f"comma list from {list(IMPLS)} (default {','.join(DEFAULT_IMPLS)})",
    )
    ap.add_argument(
        "--only",
        choices=("infinirl", "ray", "ray_numpy"),
        help="run one impl in this process and print its JSON line (used by the driver)",
    )
    bc.add_record_argument(ap)
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
        cmd = [
            sys.executable,
            os.path.abspath(__file__),
            "--only",
            impl,
            "--sizes",
            ",".join(sizes),
        ]
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
    return bc.conclude(line, bc.failures_of(results), record=(args.record, "Runtime channel benchmark"))


if __name__ == "__main__":
    sys.exit(bc.concluded("runtime_channel", main))
