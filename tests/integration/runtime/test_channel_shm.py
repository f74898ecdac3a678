"""Channel items through the producer's shared memory: between workers of one node, intact, in
place, reused; never served to a getter that cannot map them; nothing left once workers are gone."""

import asyncio
import os
import subprocess
import sys
import time

import pytest
import ray
import torch

from infinirl.runtime import Channel, ChannelError, ChannelPeerDied, Worker, WorkerGroup
from infinirl.runtime.transport import Envelope, unpack
from tests.conftest import ship_by_value

ship_by_value(__name__)

_names = iter(range(10_000))
MIB = 1 << 20
OTHER_NODE = "f" * 56  # a node id no process of this cluster runs on


def fresh(**options) -> Channel:
    return Channel.create(f"shm-{time.time_ns()}-{next(_names)}", **options)


def payload(i: int) -> dict:
    """Item ``i``: tensors of several dtypes and layouts, above the inline limit, and a plain value."""
    generator = torch.Generator().manual_seed(i)
    values = torch.randn(256, 1024, generator=generator)
    return {
        "f32": values,
        "bf16": values[:, :512].to(torch.bfloat16),
        "ids": torch.randint(0, 50_000, (4, 1000), generator=generator),
        "mask": values[0] > 0,
        "rows": values[::16, ::2],  # not contiguous
        "scalar": torch.tensor(float(i)),
        "meta": {"index": i, "tag": f"item-{i}"},
    }


def assert_payload(i: int, got: dict) -> None:
    sent = payload(i)
    assert got["meta"] == sent["meta"]
    for key in ("f32", "bf16", "ids", "mask", "rows", "scalar"):
        assert got[key].dtype == sent[key].dtype and torch.equal(got[key], sent[key]), (i, key)


def memfd_maps() -> list[str]:
    with open("/proc/self/maps") as maps:
        return [line for line in maps if "infinirl-shm" in line]


class Producer(Worker):
    def produce(self, ch: Channel, indices: list[int]):
        from infinirl.runtime import shm_pool

        for i in indices:
            ch.put(payload(i))
        ch.flush()
        return dict(shm_pool.pool().stats), os.getpid()


class Consumer(Worker):
    def consume(self, ch: Channel, n: int, batch: int = 0):
        """Check every item, modify it in place, drop it; ``batch``: take items by get_batch."""
        seen = []
        while len(seen) < n:
            items = ch.get_batch(batch, timeout=120) if batch else [ch.get(timeout=120)]
            for item in items:
                i = item["meta"]["index"]
                assert_payload(i, item)
                item["f32"].add_(1.0)  # the consumer owns the item: writable, in place
                assert torch.equal(item["f32"], payload(i)["f32"] + 1.0)
                seen.append(i)
        ch.give_back_prefetched()  # the other consumer needs whatever this one took ahead
        return seen

    def forget_and_report_maps(self) -> list[str]:
        from infinirl.runtime import shm_pool

        shm_pool.forget_stale_mappings()
        return memfd_maps()


def test_items_between_workers_are_intact_writable_and_reuse_segments(ray_cluster):
    """Two consumers on the producer's node: every item arrives once, equal to what was sent, and
    can be modified; the producer reuses a few segments; once the producer is gone, the consumers
    keep no mapping of its memory and /dev/shm holds nothing of ours."""
    shm_before = set(os.listdir("/dev/shm"))
    ch = fresh(maxsize=3, pipeline_depth=2, prefetch=2)
    consumers = WorkerGroup.launch(Consumer, "shm-consumer", num_ranks=2)
    producer = WorkerGroup.launch(Producer, "shm-producer", num_ranks=1)
    try:
        n = 40
        consuming = consumers.call_each("consume", [(ch, n // 2), (ch, n // 2, 2)])  # get, and get_batch
        stats, producer_pid = producer.produce(ch, list(range(n))).wait(timeout=300)[0]
        seen = consuming.wait(timeout=300)
        assert sorted(seen[0] + seen[1]) == list(range(n)), "every item once"
        # most items through shared memory: the first ones, and any put while the pool was full
        # (consumers slowed by a loaded host), may take the object store
        assert stats["writes"] >= n // 2, stats
        assert stats["created"] <= 12, f"segments are reused: {stats}"
        producer.shutdown()
        deadline = time.monotonic() + 60
        while os.path.exists(f"/proc/{producer_pid}") and time.monotonic() < deadline:
            time.sleep(0.1)
        assert consumers.forget_and_report_maps().wait(timeout=60) == [[], []]
        assert set(os.listdir("/dev/shm")) <= shm_before
    finally:
        producer.shutdown()
        consumers.shutdown()


def test_an_item_a_cancelled_get_took_goes_back_intact(ray_cluster):
    ch = fresh()
    producer = WorkerGroup.launch(Producer, "shm-giver", num_ranks=1)

    async def scenario():
        getter = asyncio.ensure_future(ch.get_async())
        await asyncio.sleep(1.0)  # the get now waits on the channel's actor (and registered this consumer)
        stats, _ = producer.produce(ch, [7, 8]).wait(timeout=120)[0]  # blocking: the get takes item 7
        getter.cancel()  # ...and its caller is cancelled before it received it
        with pytest.raises(asyncio.CancelledError):
            await getter
        return stats

    try:
        stats = asyncio.run(scenario())
        assert stats["writes"] == 2, "both items went through shared memory"
        first, second = ch.get(timeout=30), ch.get(timeout=30)
        assert_payload(7, first)  # given back to the front of the queue, still valid
        assert_payload(8, second)
    finally:
        producer.shutdown()
        ch.destroy()


def test_an_item_whose_producer_exited_unread_fails_with_the_cause(ray_cluster):
    ch = fresh()
    ch.register_consumer()  # the driver: a consumer on the producer's node
    producer = WorkerGroup.launch(Producer, "shm-gone", num_ranks=1)
    try:
        stats, pid = producer.produce(ch, [3]).wait(timeout=120)[0]
        assert stats["writes"] == 1
    finally:
        producer.shutdown()
    deadline = time.monotonic() + 60
    while os.path.exists(f"/proc/{pid}") and time.monotonic() < deadline:
        time.sleep(0.1)
    unreadable = f"shared memory of pid {pid} cannot be read: that process exited"
    with pytest.raises(ChannelError, match=unreadable):
        ch.get(timeout=30)


def test_an_unreadable_item_in_a_batch_loses_only_itself(ray_cluster):
    """The items a batch get took with an unreadable one go back to the queue in their order (the
    one read before it re-packed), and its error is raised."""
    ch = fresh()
    ch.register_consumer()
    ch.put("first")
    producer = WorkerGroup.launch(Producer, "shm-gone-batch", num_ranks=1)
    try:
        pid = producer.produce(ch, [3]).wait(timeout=120)[0][1]
    finally:
        producer.shutdown()
    ch.put("last")
    deadline = time.monotonic() + 60
    while os.path.exists(f"/proc/{pid}") and time.monotonic() < deadline:
        time.sleep(0.1)
    with pytest.raises(ChannelError, match=f"shared memory of pid {pid} cannot be read"):
        ch.get_batch(3, timeout=30)
    assert ch.get_batch(2, timeout=30) == ["first", "last"]


def _raw_get(ch: Channel, node: str, timeout: float = 30):
    """A get as a process on ``node`` would make it (pid 1: not this process), returning the envelope itself."""
    envelope, _ = ray.get(ch._actor.get.remote("default", 1, "test-getter", timeout, node=node),
                          timeout=timeout + 30)
    return envelope


def _register_consumer(ch: Channel, node: str, pid: int, label: str):
    """A consumer process on ``node`` as the channel sees it (no host: watched by pid on this node)."""
    return ray.get(ch._actor.register.remote(f"process:{node}:{pid}", "consumer", label, None, node, pid, 0))


def test_the_object_store_carries_items_to_a_consumer_on_another_node(ray_cluster):
    here = ray.get_runtime_context().get_node_id()
    ch = fresh()
    pids, nodes = _register_consumer(ch, OTHER_NODE, 4242, "remote consumer")
    assert nodes == [OTHER_NODE]
    ch.put(torch.ones(MIB))
    assert _raw_get(ch, OTHER_NODE).path == "object_store"

    local = fresh()
    _register_consumer(local, here, os.getpid(), "consumer on this node")  # not this process: no by-reference
    local.put(torch.ones(MIB))  # the only consumer is on this node: shared memory
    local.put(torch.full((MIB,), 2.0))
    with pytest.raises(TimeoutError):
        _raw_get(local, OTHER_NODE, timeout=1)  # never handed to a getter that cannot map it
    _register_consumer(local, OTHER_NODE, 4242, "remote consumer, registered late")
    local.put(torch.full((MIB,), 3.0))  # decided by the reply of the put before: still shared memory
    local.put(torch.full((MIB,), 4.0))  # the consumer elsewhere is known now: the object store
    remote = _raw_get(local, OTHER_NODE)
    assert remote.path == "object_store" and remote.producer_node == here
    assert [float(local.get(timeout=30)[0]) for _ in range(3)] == [1.0, 2.0, 3.0]  # the pinned ones, here


def test_pinned_items_nobody_on_their_node_can_take_are_dropped_loudly(ray_cluster):
    """Every consumer on the producer's node died: a getter elsewhere is told and the items go,
    instead of waiting forever (and holding the key's capacity) for items it cannot map."""
    here = ray.get_runtime_context().get_node_id()
    ch = fresh(maxsize=3)
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait(timeout=60)
    _register_consumer(ch, here, gone.pid, "a consumer that exited")
    ch.put("for anyone")
    pinned = Envelope("shm", os.getpid(), here, body=None, nbytes=MIB)
    ray.get(ch._actor.put.remote(pinned, "default", 1.0, 30))
    ray.get(ch._actor.put.remote(pinned, "default", 1.0, 30))  # the key is full
    batch = ray.get(ch._actor.get_batch.remote(5, "default", 1, "test-getter", 30, node=OTHER_NODE), timeout=60)
    assert [envelope.body for envelope, _ in batch] == ["for anyone"], "a batch returns what it took"
    assert ch.qsize() == 2, "the next get reports the stranded items"
    with pytest.raises(ChannelPeerDied, match=r"2 item\(s\) of key 'default' were put in shared memory on node"):
        _raw_get(ch, OTHER_NODE)
    assert ch.qsize() == 0
    ch.put("room again", timeout=5)
    assert _raw_get(ch, OTHER_NODE).body == "room again"


def test_an_async_producer_learns_the_consumers_from_its_registration(ray_cluster):
    here = ray.get_runtime_context().get_node_id()
    ch = fresh()
    _register_consumer(ch, here, os.getpid(), "consumer on this node")
    asyncio.run(ch.put_async({"x": torch.arange(MIB)}))  # its first item: shared memory already
    envelope = _raw_get(ch, here)
    assert envelope.path == "shm"
    assert torch.equal(unpack(envelope)["x"], torch.arange(MIB))
