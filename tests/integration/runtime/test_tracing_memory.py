"""Tracing (spans -> Chrome trace, busy ratio) and the device lock that collocated components share."""

import json
import time

import pytest

from infinirl.runtime import Tracer, Worker, WorkerError, WorkerGroup, device_turn
from infinirl.runtime.tracing import union_length
from tests.conftest import ship_by_value

ship_by_value(__name__)


def test_union_length_against_brute_force():
    import random

    rng = random.Random(0)
    for _ in range(200):
        intervals = [(a, a + rng.uniform(0, 3)) for a in (rng.uniform(0, 10) for _ in range(rng.randint(0, 6)))]
        grid = [i / 1000 for i in range(14000)]
        brute = sum(1 for t in grid if any(s <= t < e for s, e in intervals)) / 1000
        assert abs(union_length(intervals) - brute) < 0.02


def test_busy_ratio_and_chrome_trace(tmp_path):
    tracer = Tracer()
    tracer.add("rollout", 0, "generate", 0.0, 2.0)
    tracer.add("actor", 0, "train", 2.0, 3.0)
    tracer.add("rollout", 0, "generate", 3.0, 4.0)
    tracer.device_of = {("rollout", 0): ["gpu0"], ("actor", 0): ["gpu0"]}
    assert tracer.busy_ratio() == {"gpu0": pytest.approx(1.0)}
    tracer.device_of = {("rollout", 0): ["gpu0"], ("actor", 0): ["gpu1"]}
    ratios = tracer.busy_ratio()
    assert ratios["gpu0"] == pytest.approx(0.75) and ratios["gpu1"] == pytest.approx(0.25)
    path = tracer.write_chrome_trace(str(tmp_path / "trace.json"))
    events = json.load(open(path))["traceEvents"]
    spans = [e for e in events if e["ph"] == "X"]
    assert len(spans) == 3 and {e["name"] for e in spans} == {"generate", "train"}
    assert spans[0]["dur"] == pytest.approx(2e6)


class Sharer(Worker):
    def __init__(self):
        self.loaded = False
        self.events = []

    def reload(self):
        self.loaded = True

    def offload(self):
        self.loaded = False

    def take_turn(self, seconds):
        with device_turn(self, devices=["shared-device"]):
            assert self.loaded
            start = time.time()
            time.sleep(seconds)
            return (start, time.time())

    def is_loaded(self):
        return self.loaded


def test_collocated_components_take_turns_and_spans_are_recorded(ray_cluster):
    a = WorkerGroup.launch(Sharer, "rollout", num_ranks=1)
    b = WorkerGroup.launch(Sharer, "actor", num_ranks=1)
    try:
        ha, hb = a.take_turn(1.0), b.take_turn(1.0)
        (sa, ea), (sb, eb) = ha.wait(timeout=60)[0], hb.wait(timeout=60)[0]
        assert ea <= sb or eb <= sa, "the device lock must serialise the two turns"
        assert a.is_loaded().wait() == [False], "offload runs when the turn ends"
        tracer = Tracer()
        tracer.collect(a, b)
        methods = {(s[0], s[2]) for s in tracer.spans}
        assert ("rollout", "take_turn") in methods and ("actor", "take_turn") in methods
    finally:
        a.shutdown()
        b.shutdown()


class DiesHolding(Sharer):
    def hold_and_die(self):
        import os

        with device_turn(self, devices=["shared-device"]):
            os._exit(5)

    def pid(self):
        import os

        return os.getpid()


def test_a_holder_that_dies_holding_the_devices_frees_them(ray_cluster, deliberate_deaths):
    dying = WorkerGroup.launch(DiesHolding, "dies-holding", num_ranks=1)
    other = WorkerGroup.launch(Sharer, "waits", num_ranks=1)
    deliberate_deaths(*dying.pid().wait(timeout=60))
    try:
        with pytest.raises(WorkerError, match="died"):
            dying.hold_and_die().wait(timeout=60)
        start, end = other.take_turn(0.1).wait(timeout=60)[0]
        assert end > start
    finally:
        dying.shutdown()
        other.shutdown()


def test_the_device_lock_forgets_waiters_that_timed_out_or_were_cancelled():
    import asyncio

    from infinirl.runtime.memory import _DeviceLockActor

    async def main():
        lock = _DeviceLockActor()
        await lock.acquire(["d"], "a", None)
        with pytest.raises(TimeoutError, match=r"b waited 0.05s for devices held by \{'d': 'a'\}"):
            await lock.acquire(["d"], "b", 0.05)
        cancelled = asyncio.ensure_future(lock.acquire(["d"], "c", None))
        await asyncio.sleep(0.01)
        cancelled.cancel()
        await asyncio.sleep(0.01)
        await lock.release(["d"], "a")
        await asyncio.wait_for(lock.acquire(["d"], "e", None), 5)  # neither b nor c got it
        return await lock.holders()

    assert asyncio.run(main()) == {"d": "e"}
