"""Channel: a producer or consumer that dies never leaves the other side waiting forever."""

import asyncio
import os
import signal
import threading
import time

import pytest
import ray

from infinirl.runtime import Channel, ChannelPeerDied, RestartPolicy, Worker, WorkerGroup
from tests.conftest import ship_by_value

ship_by_value(__name__)

_names = iter(range(10_000))


def fresh(maxsize=0, prefetch=1) -> Channel:
    return Channel.create(f"peers-{time.time_ns()}-{next(_names)}", maxsize=maxsize, prefetch=prefetch)


class Peer(Worker):
    def produce(self, channels: list, items: list):
        for ch in channels:
            ch.register_producer()
        for item in items:
            channels[0].put(item, key="k")
        return os.getpid()

    def take(self, ch: Channel):
        return ch.get(key="k")

    def register_consumer(self, ch: Channel):
        ch.register_consumer()
        return os.getpid()

    def pid(self):
        return os.getpid()


@ray.remote(num_cpus=0)
class PrefetchingConsumer:
    """A plain Ray actor (no worker host): the channel watches it through its pid."""

    def __init__(self, ch: Channel):
        self.ch = ch

    def take(self, n: int) -> list:
        return [self.ch.get(key="k", timeout=60) for _ in range(n)]

    def pid(self) -> int:
        return os.getpid()


def _in_thread(fn, *args, **kwargs):
    """Run ``fn`` on a thread; returns a function that joins it and gives its result or error."""
    out = {}

    def run():
        try:
            out["result"] = fn(*args, **kwargs)
        except BaseException as exc:  # handed to the test thread
            out["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()

    def join():
        thread.join(timeout=120)
        assert not thread.is_alive(), "the call is still blocked"
        return out

    return join


def _wait_until(condition, what: str, limit_s: float = 60.0) -> None:
    deadline = time.monotonic() + limit_s
    while not condition():
        assert time.monotonic() < deadline, f"{what} did not happen"
        time.sleep(0.1)


def _peer_roles(ch: Channel) -> dict:
    return {name: peer for name, peer in ch.info()["peers"].items() if name.startswith("peer[")}


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_getters_learn_that_every_producer_died(ray_cluster, deliberate_deaths):
    ch = fresh()
    prefetching = fresh(prefetch=4)  # its gets take several items per call (get_many)
    group = WorkerGroup.launch(Peer, "peer", num_ranks=1)
    try:
        pid = group.produce([ch, prefetching], ["first", "second"]).wait(timeout=60)[0]
        assert ch.get(key="k", timeout=30) == "first"
        blocked = [_in_thread(ch.get, key="k2", timeout=90)]  # waits on an empty key
        deliberate_deaths(pid)
        os.kill(pid, signal.SIGKILL)
        error = blocked[0]().get("error")
        assert isinstance(error, ChannelPeerDied), error
        text = str(error)
        assert f"channel '{ch.name}'" in text and "key 'k2'" in text
        assert "every producer of the channel has died" in text and "peer[rank 0]" in text and str(pid) in text
        assert ch.get(key="k", timeout=30) == "second"  # what was put is still delivered
        for call in (lambda: ch.get(key="k", timeout=30),
                     lambda: ch.get_batch(5, key="k", timeout=30),
                     lambda: prefetching.get(key="k", timeout=30),
                     lambda: asyncio.run(ch.get_async(key="k", timeout=30)),
                     lambda: asyncio.run(ch.get_batch_async(5, key="k", timeout=30))):
            with pytest.raises(ChannelPeerDied, match="every producer of the channel has died"):
                call()
    finally:
        group.shutdown()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_a_producer_that_never_put_anything_is_watched_too(ray_cluster, deliberate_deaths):
    ch = fresh()
    group = WorkerGroup.launch(Peer, "peer", num_ranks=1)
    try:
        pid = group.produce([ch], []).wait(timeout=60)[0]  # registers, puts nothing
        deliberate_deaths(pid)
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(ChannelPeerDied, match=r"no item for key 'k' and every producer .* has died"):
            ch.get_batch(3, key="k", timeout=90)
    finally:
        group.shutdown()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_a_producer_waiting_for_space_learns_that_every_consumer_died(ray_cluster, deliberate_deaths):
    ch = fresh(maxsize=1)
    group = WorkerGroup.launch(Peer, "peer", num_ranks=1)
    try:
        pid = group.register_consumer(ch).wait(timeout=60)[0]
        ch.put("fills key k", key="k")
        blocked = _in_thread(ch.put, "waits for space", key="k", timeout=90)
        deliberate_deaths(pid)
        os.kill(pid, signal.SIGKILL)
        error = blocked().get("error")
        assert isinstance(error, ChannelPeerDied), error
        text = str(error)
        assert f"channel '{ch.name}'" in text and "put on key 'k' waits for space" in text
        assert "every consumer of the channel has died" in text and "peer[rank 0]" in text
    finally:
        group.shutdown()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_a_dead_consumers_pending_get_takes_nothing(ray_cluster, deliberate_deaths):
    """The get a consumer had pending when it died must not take the next item: nobody would
    receive it."""
    ch = fresh()
    group = WorkerGroup.launch(Peer, "peer", num_ranks=1)
    try:
        pid = group.pids()[0]
        group.take(ch)  # blocks in the rank: the channel is empty
        _wait_until(lambda: _peer_roles(ch), "the rank's registration as a consumer")
        deliberate_deaths(pid)
        os.kill(pid, signal.SIGKILL)
        _wait_until(lambda: all(p["death"] for p in _peer_roles(ch).values()), "the channel noticing the death")
        ch.put("not lost", key="k")
        assert ch.get(key="k", timeout=30) == "not lost"
    finally:
        group.shutdown()


def test_a_cancelled_async_get_gives_back_what_it_took(ray_cluster):
    """The actor hands an item to a waiting get whose caller is cancelled before it receives it: the
    item goes back to the front of its queue instead of vanishing with the cancelled call."""
    ch = Channel.create(f"give-back-{time.time_ns()}")

    async def scenario():
        getter = asyncio.ensure_future(ch.get_async())
        await asyncio.sleep(1.0)  # the get now waits on the channel's actor
        ch.put("kept")  # blocking: the actor hands "kept" to that get before this loop runs again
        ch.put("second")
        getter.cancel()  # ...and the caller is cancelled before it received it
        with pytest.raises(asyncio.CancelledError):
            await getter

    try:
        asyncio.run(scenario())
        assert [ch.get(timeout=10), ch.get(timeout=10)] == ["kept", "second"]  # in order, nothing lost
    finally:
        ch.destroy()


def test_a_killed_prefetching_consumers_items_go_to_another_consumer(ray_cluster, deliberate_deaths):
    """A consumer that took items ahead and is killed before handing them out: another consumer
    gets every one of them, in order, and nothing the killed one had handed out in an earlier
    round trip (acknowledged by its next one) comes twice."""
    ch = fresh(prefetch=4)
    for i in range(8):
        ch.put(i, key="k")
    consumer = PrefetchingConsumer.remote(ch)
    # Round trip 1 takes 0..3 (1..3 leased); round trip 2 says those are handed out, takes 4..7 and
    # hands out 4: 5, 6, 7 are leased to the consumer, handed out to nobody.
    assert ray.get(consumer.take.remote(5), timeout=60) == [0, 1, 2, 3, 4]
    assert ch.qsize(key="k") == 0 and ch.info()["leased"] == 3
    deliberate_deaths(ray.get(consumer.pid.remote(), timeout=60))
    ray.kill(consumer)
    _wait_until(lambda: ch.info()["requeued_from_dead"] == 3, "the channel re-queueing the dead consumer's lease")
    other = Channel.connect(ch.name)  # prefetches too: its first get takes all three
    assert [other.get(key="k", timeout=30) for _ in range(3)] == [5, 6, 7]
    with pytest.raises(TimeoutError):  # nothing comes twice
        other.get(key="k", timeout=1)
    info = ch.info()
    assert info["leased"] == 0 and info["lost_with_dead"] == 0, info  # the last get settled other's lease
    ch.destroy()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_a_restarted_ranks_old_process_gives_its_prefetched_items_back(ray_cluster, deliberate_deaths):
    """Ray restarts a rank under the same actor (the same consumer to the channel), but its new
    process holds nothing: the items the old process took ahead go back to the queue."""
    ch = fresh(prefetch=4)
    for i in range(4):
        ch.put(i, key="k")
    group = WorkerGroup.launch(Peer, "peer", num_ranks=1, restart=RestartPolicy(max_restarts=1, retry_calls=False))
    try:
        first_pid = group.pids()[0]
        assert group.take(ch).wait(timeout=60) == [0]  # 1, 2, 3 wait in the rank's buffer
        deliberate_deaths(first_pid)
        os.kill(first_pid, signal.SIGKILL)
        _wait_until(lambda: ch.info()["requeued_from_dead"] == 3, "the channel re-queueing the old process's lease",
                    limit_s=120)
        assert [ch.get(key="k", timeout=30) for _ in range(3)] == [1, 2, 3]
        assert group.pid().wait(timeout=60)[0] != first_pid, "the rank runs in a new process"
        assert all(not p["death"] for p in _peer_roles(ch).values()), "a restarted rank is alive"
    finally:
        group.shutdown()
        ch.destroy()
