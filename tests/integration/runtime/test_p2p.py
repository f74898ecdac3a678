"""Point-to-point channel items: a failed pull leaves the pair usable, async getters never block
the event loop that serves their own rank's pulls."""

import time

import pytest
import torch

from infinirl.runtime import Channel, Worker, WorkerError, WorkerGroup
from tests.conftest import ship_by_value

ship_by_value(__name__)

PULL_S = 60  # far below the pair group's 300-s timeout: a pull that waits on it fails the test


def p2p_channel(name: str) -> Channel:
    return Channel.create(f"{name}-{time.time_ns()}", transport="p2p")


class Producer(Worker):
    def put(self, ch: Channel, value: float, lose: bool = False) -> float:
        ch.put(torch.full((1000, 100), value))
        if lose:
            # What a put whose reply was lost does (it discards the item the channel still queued):
            # its consumer pulls an item the producer no longer holds, and the serve fails.
            from infinirl.runtime import p2p

            for item in list(p2p._outbox):
                p2p.release(item)
        return value


class Consumer(Worker):
    def take(self, ch: Channel) -> float:
        return float(ch.get(timeout=PULL_S)[0, 0])


def test_a_failed_pull_leaves_the_pair_usable(ray_cluster):
    """After a serve failed, both sides give the pair's group up: the next items arrive (the pull
    left pending on the old group cannot catch them) instead of waiting for the group's timeout."""
    ch = p2p_channel("p2p-retry")
    producer = WorkerGroup.launch(Producer, "p2p-retry-producer", num_ranks=1)
    consumer = WorkerGroup.launch(Consumer, "p2p-retry-consumer", num_ranks=1)
    try:
        producer.put(ch, 1.0).wait(timeout=PULL_S)
        assert consumer.take(ch).wait(timeout=PULL_S) == [1.0]  # the pair's group is made
        producer.put(ch, 2.0, lose=True).wait(timeout=PULL_S)
        with pytest.raises(WorkerError, match="no longer held by process"):
            consumer.take(ch).wait(timeout=PULL_S)
        for value in (3.0, 4.0):
            producer.put(ch, value).wait(timeout=PULL_S)
            assert consumer.take(ch).wait(timeout=PULL_S) == [value]
    finally:
        producer.shutdown()
        consumer.shutdown()


class AsyncPeer(Worker):
    async def swap(self, out: Channel, inp: Channel, value: float) -> float:
        await out.put_async(torch.full((1000, 100), value))
        item = await inp.get_async(timeout=PULL_S)
        return float(item[0, 0])

    async def swap_batch(self, out: Channel, inp: Channel, value: float) -> float:
        await out.put_async(torch.full((1000, 100), value))
        (item,) = await inp.get_batch_async(1, timeout=PULL_S)
        return float(item[0, 0])


def test_async_ranks_pulling_from_each_other_do_not_deadlock(ray_cluster):
    """Each rank's pull needs the other rank's event loop to serve it: the pulls must not hold the
    loops they wait on."""
    a, b = p2p_channel("p2p-swap-a"), p2p_channel("p2p-swap-b")
    peers = WorkerGroup.launch(AsyncPeer, "p2p-swap", num_ranks=2)
    try:
        assert peers.call_each("swap_batch", [(a, b, 3.0), (b, a, 4.0)]).wait(timeout=PULL_S) == [4.0, 3.0]
        assert peers.call_each("swap", [(a, b, 1.0), (b, a, 2.0)]).wait(timeout=PULL_S) == [2.0, 1.0]
    finally:
        peers.shutdown()
