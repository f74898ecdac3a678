"""Point-to-point channel items: a failed pull leaves the pair usable."""

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
