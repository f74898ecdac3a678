"""Channel: per-key FIFO, weighted batches, back-pressure, close, many producers/consumers, paths."""

import asyncio
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from infinirl.runtime import Channel, ChannelClosed, ChannelError, Worker, WorkerError, WorkerGroup
from infinirl.runtime.transport import pack, unpack
from tests.conftest import ship_by_value

ship_by_value(__name__)

_names = iter(range(10_000))


def fresh(maxsize=0) -> Channel:
    return Channel.create(f"test-{time.time_ns()}-{next(_names)}", maxsize=maxsize)


def test_per_key_fifo_and_keys_independent(ray_cluster):
    ch = fresh()
    for i in range(20):
        ch.put(("a", i), key="a")
        ch.put(("b", i), key="b")
    assert [ch.get(key="b") for _ in range(20)] == [("b", i) for i in range(20)]
    assert [ch.get(key="a") for _ in range(20)] == [("a", i) for i in range(20)]


def test_get_batch_never_exceeds_target_weight(ray_cluster):
    ch = fresh()
    for w in [3, 1, 4, 1, 5, 9, 2, 6]:
        ch.put(w, weight=w)
    assert ch.get_batch(target_weight=8) == [3, 1, 4]  # reaches the target exactly
    assert ch.get_batch(target_weight=8) == [1, 5]  # 9 more would exceed it: it waits for the next batch
    assert ch.get_batch(target_weight=8) == [9]  # heavier than the target: alone
    ch.close()
    assert ch.get_batch(target_weight=100) == [2, 6]  # closed: what is left
    with pytest.raises(ChannelClosed):
        ch.get_batch(target_weight=1)


def test_get_batch_weights_add_up_exactly(ray_cluster):
    """Batches take items in FIFO order and never pass the target; a short batch is returned as
    soon as the next item would pass it (the items are all still delivered, in order)."""
    ch = fresh()
    weights = [2, 3, 1, 1, 4, 2, 2, 5, 1]
    for i, w in enumerate(weights):
        ch.put(i, weight=w)
    ch.close()
    batches = []
    while True:
        try:
            batches.append(ch.get_batch(target_weight=5))
        except ChannelClosed:
            break
    assert [x for batch in batches for x in batch] == list(range(len(weights)))
    assert all(sum(weights[i] for i in batch) <= 5 for batch in batches)
    assert batches == [[0, 1], [2, 3], [4], [5, 6], [7], [8]]


def test_bad_weights_and_targets_are_refused(ray_cluster):
    ch = fresh()
    for weight in (-1, 0, float("nan"), float("inf"), "heavy"):
        with pytest.raises(ValueError, match=f"channel '{ch.name}': weight must be a finite number > 0"):
            ch.put("x", weight=weight)
        with pytest.raises(ValueError, match="weight must be a finite number > 0"):
            asyncio.run(ch.put_async("x", weight=weight))
    with pytest.raises(ValueError, match="weights must be a finite number > 0, got 0"):
        ch.put_many(["a", "b"], weights=[1, 0])
    with pytest.raises(ValueError, match="put_many got 2 items but 1 weights"):
        ch.put_many(["a", "b"], weights=[1])
    for target in (0, -2, float("nan")):
        with pytest.raises(ValueError, match=f"channel '{ch.name}': target_weight must be a number > 0"):
            ch.get_batch(target)
        with pytest.raises(ValueError, match="target_weight must be a number > 0"):
            asyncio.run(ch.get_batch_async(target))
    assert ch.qsize() == 0  # nothing got in


def test_capacity_is_per_key(ray_cluster):
    """One key filling up must not block another: a consumer reading key 'a' while a producer
    fills key 'b' (with one maxsize shared by all keys, both would wait forever)."""
    ch = fresh(maxsize=2)
    ch.put("b0", key="b")
    ch.put("b1", key="b")  # key 'b' is full
    ch.put("a0", key="a", timeout=30)  # key 'a' still has room
    ch.put("a1", key="a", timeout=30)
    assert ch.get(key="a", timeout=30) == "a0"
    with pytest.raises(TimeoutError, match=f"channel '{ch.name}': put on key 'b' timed out after 0.3s"):
        ch.put("b2", key="b", timeout=0.3)
    assert ch.info()["weight_by_key"] == {"'a'": 1.0, "'b'": 2.0}
    assert ch.get(key="b") == "b0"
    ch.put("b2", key="b", timeout=30)  # room again
    assert [ch.get(key="b"), ch.get(key="b")] == ["b1", "b2"]


def test_backpressure_blocks_until_space(ray_cluster):
    ch = fresh(maxsize=2)
    ch.put(0)
    ch.put(1)
    with pytest.raises(TimeoutError):
        ch.put(2, timeout=0.3)
    done = threading.Event()

    def producer():
        ch.put(2)
        done.set()

    thread = threading.Thread(target=producer)
    thread.start()
    time.sleep(0.5)
    assert not done.is_set(), "put must block while the channel is full"
    assert ch.get() == 0
    thread.join(timeout=30)
    assert done.is_set()
    assert [ch.get(), ch.get()] == [1, 2]


def test_item_that_can_never_fit_is_rejected(ray_cluster):
    ch = fresh(maxsize=4)
    with pytest.raises(ChannelError, match="can never fit maxsize=4"):
        ch.put("big", weight=5)


def test_get_on_closed_channel(ray_cluster):
    ch = fresh()
    ch.put("last")
    ch.close()
    assert ch.get() == "last"
    with pytest.raises(ChannelClosed, match="closed"):
        ch.get()
    with pytest.raises(ChannelClosed):
        ch.put("late")


def test_get_timeout_names_channel_and_key(ray_cluster):
    ch = fresh()
    with pytest.raises(TimeoutError, match=f"channel '{ch.name}': get on key 'k' timed out after 0.2s"):
        ch.get(key="k", timeout=0.2)
    with pytest.raises(TimeoutError, match=f"channel '{ch.name}': get_batch on key 'k' timed out"):
        ch.get_batch(3, key="k", timeout=0.2)
    ch.put("only", key="k")
    assert ch.get_batch(3, key="k", timeout=0.5) == ["only"]  # the timeout ends a short batch


def test_an_abandoned_get_takes_nothing(ray_cluster):
    """A cancelled caller abandons its get: an abandon that arrives first makes the get end
    without taking anything; a get_batch abandoned halfway puts back what it had taken."""
    import ray

    ch = fresh()
    ch.put("a")
    ray.get(ch._actor.abandon.remote("early"))
    assert ray.get(ch._actor.get.remote("default", 0, "nobody", 30, request="early"), timeout=30) is None
    partial = ch._actor.get_batch.remote(3, "default", 0, "nobody", None, request="halfway")
    deadline = time.monotonic() + 30
    while ch.qsize() and time.monotonic() < deadline:  # it took "a" and waits for more
        time.sleep(0.05)
    assert ch.qsize() == 0
    ray.get(ch._actor.abandon.remote("halfway"))
    assert ray.get(partial, timeout=30) is None
    assert ch.get(timeout=5) == "a"
    assert ch.info()["get"] == 1


def test_duplicate_create_and_missing_connect(ray_cluster):
    ch = fresh()
    with pytest.raises(ChannelError, match="already exists"):
        Channel.create(ch.name)
    assert Channel.create(ch.name, exist_ok=True).name == ch.name
    with pytest.raises(ChannelError, match="no channel named"):
        Channel.connect("never-created", timeout_s=0.3)


@dataclass
class Sample:
    tokens: torch.Tensor
    reward: float


@pytest.mark.parametrize("nbytes", [16, 1 << 20])
def test_payload_kinds_roundtrip_through_worker(ray_cluster, nbytes):
    ch = fresh()
    big = torch.arange(nbytes // 4, dtype=torch.float32)
    payloads = [
        big,
        big.to(torch.bfloat16),
        {"x": big, "nested": [big[:3], (big[:2], "tag")]},
        TensorDict({"ids": big.reshape(-1, 1)}, batch_size=[big.numel()]),
        Sample(tokens=big, reward=1.5),
        {"plain": "python object", "n": 3},
    ]
    group = WorkerGroup.launch(Relay, "relay", num_ranks=1)
    try:
        out = fresh()
        handle = group.relay(ch, out, len(payloads))
        for p in payloads:
            ch.put(p)
        handle.wait(timeout=60)
        for sent in payloads:
            got = out.get()
            _assert_same(sent, got)
    finally:
        group.shutdown()


def _assert_same(a, b):
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and torch.equal(a, b)
    elif isinstance(a, TensorDict):
        assert a.batch_size == b.batch_size and torch.equal(a["ids"], b["ids"])
    elif isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _assert_same(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b)
        for x, y in zip(a, b):
            _assert_same(x, y)
    elif isinstance(a, Sample):
        assert isinstance(b, Sample) and b.reward == a.reward
        _assert_same(a.tokens, b.tokens)
    else:
        assert a == b


class Relay(Worker):
    def relay(self, inbox: Channel, outbox: Channel, n: int):
        for _ in range(n):
            outbox.put(inbox.get())


class Producer(Worker):
    def produce(self, ch: Channel, start: int, count: int):
        for i in range(start, start + count, 50):
            ch.put_many(list(range(i, min(i + 50, start + count))), key="k")


class Consumer(Worker):
    def consume(self, ch: Channel):
        got = []
        while True:
            try:
                got.extend(ch.get_batch(25, key="k"))
            except Exception as exc:  # ChannelClosed once drained
                assert "closed" in str(exc)
                return got


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_many_producers_consumers_nothing_lost_nothing_duplicated(ray_cluster):
    ch = fresh(maxsize=500)
    producers = WorkerGroup.launch(Producer, "producer", num_ranks=4)
    consumers = WorkerGroup.launch(Consumer, "consumer", num_ranks=3)
    try:
        consuming = consumers.consume(ch)
        producers.call_each("produce", [(ch, r * 2500, 2500) for r in range(4)]).wait(timeout=300)
        ch.close()
        results = consuming.wait(timeout=300)
        everything = [x for per_rank in results for x in per_rank]
        assert len(everything) == 10_000
        assert sorted(everything) == list(range(10_000))
        for per_rank in results:  # per-producer order survives (FIFO per key)
            for r in range(4):
                mine = [x for x in per_rank if r * 2500 <= x < (r + 1) * 2500]
                assert mine == sorted(mine)
        assert all(len(per_rank) > 0 for per_rank in results), "work should spread over consumers"
    finally:
        producers.shutdown()
        consumers.shutdown()


def test_async_api(ray_cluster):
    ch = fresh()

    async def main():
        await ch.put_async({"a": torch.ones(3)}, weight=2)
        got = await ch.get_async()
        await ch.put_async(1)
        await ch.put_async(2)
        batch = await ch.get_batch_async(2)
        return got, batch

    got, batch = asyncio.run(main())
    assert torch.equal(got["a"], torch.ones(3)) and batch == [1, 2]


def test_transport_paths(ray_cluster):
    small = pack(torch.ones(8))
    assert small.path == "inline"
    large = pack(torch.ones(1 << 20))
    assert large.path == "object_store" and large.nbytes == 4 << 20
    assert torch.equal(unpack(large), torch.ones(1 << 20))
    frames = {"camera": [np.full((128, 128, 3), i, dtype=np.uint8) for i in range(4)]}  # 192 KiB of numpy
    episode = pack(frames)
    assert episode.path == "object_store" and episode.nbytes == 4 * 128 * 128 * 3  # not through the actor
    assert all((got == i).all() for i, got in enumerate(unpack(episode)["camera"]))
    payload = {"t": torch.ones(1 << 20)}
    local = pack(payload, same_process=True)
    assert local.path == "local" and unpack(local) is payload  # handed over by reference


def test_same_process_consumer_gets_reference(ray_cluster):
    ch = fresh()
    ch.register_consumer()
    ch.put("warm-up")  # learns that the only consumer is this process
    assert ch.get() == "warm-up"
    tensor = torch.ones(1 << 20)
    ch.put(tensor)
    assert ch.get() is tensor


class P2PProducer(Worker):
    def produce(self, ch: Channel, n: int):
        from infinirl.runtime import p2p

        assert p2p.available(), "a Worker process must be able to serve p2p pulls"
        sent = []
        for i in range(n):
            item = {"x": torch.full((1000, 257), float(i)), "ids": torch.arange(i, i + 5), "meta": i}
            ch.put(item)
            sent.append(float(item["x"].sum()))
        return sent

    def outbox_after_a_refused_put(self, full: Channel) -> int:
        from infinirl.runtime import p2p

        full.put(torch.zeros(1000))
        with pytest.raises(TimeoutError):
            full.put(torch.ones(1000), timeout=0.2)
        return len(p2p._outbox)  # the queued item's tensors only: the refused one's are released


class P2PConsumer(Worker):
    def consume(self, ch: Channel, n: int):
        got = []
        for _ in range(n):
            item = ch.get(timeout=120)
            assert item["ids"].tolist() == list(range(item["meta"], item["meta"] + 5))
            got.append(float(item["x"].sum()))
        return got


def test_p2p_transport_between_workers(ray_cluster):
    """Tensors go producer -> consumer over a pairwise gloo group (NCCL on GPU), not the store."""
    ch = Channel.create(f"p2p-{time.time_ns()}", transport="p2p")
    assert Channel.connect(ch.name).transport == "p2p"
    producer = WorkerGroup.launch(P2PProducer, "p2p-producer", num_ranks=1)
    consumer = WorkerGroup.launch(P2PConsumer, "p2p-consumer", num_ranks=1)
    try:
        got = consumer.consume(ch, 6)
        sent = producer.produce(ch, 6).wait(timeout=120)[0]
        assert got.wait(timeout=120)[0] == sent
        full = Channel.create(f"p2p-full-{time.time_ns()}", transport="p2p", maxsize=1)
        assert producer.outbox_after_a_refused_put(full).wait(timeout=60) == [1]
        # Items whose producer died before serving them, from a producer the consumer has a pair
        # group with and from one it has none with yet: the pull ends at once with that error, not
        # after the pair group's 300-s timeout.
        stranger = WorkerGroup.launch(P2PProducer, "p2p-producer-2", num_ranks=1)
        orphaned = {}
        for group in (producer, stranger):
            orphaned[group.component] = Channel.create(f"p2p-orphan-{time.time_ns()}", transport="p2p")
            group.produce(orphaned[group.component], 1).wait(timeout=60)
            group.shutdown()
        start = time.monotonic()
        for ch in orphaned.values():
            with pytest.raises(WorkerError, match="the producer could not send it"):
                consumer.consume(ch, 1).wait(timeout=120)
        assert time.monotonic() - start < 60
    finally:
        producer.shutdown()
        consumer.shutdown()
    with pytest.raises(ChannelError, match="transport='nccl'"):
        Channel.create("bad-transport", transport="nccl")


class PipelinedProducer(Worker):
    def produce(self, ch: Channel, start: int, count: int):
        for i in range(start, start + count):
            ch.put(i, key="k")
        ch.flush()
        return count


def test_pipelined_puts_keep_order_and_backpressure(ray_cluster):
    ch = Channel.create(f"pipe-{time.time_ns()}", maxsize=5, pipeline_depth=4)
    assert Channel.connect(ch.name).pipeline_depth == 4
    reader = Channel.create(f"pipe-read-{time.time_ns()}", prefetch=8)
    producers = WorkerGroup.launch(PipelinedProducer, "pipe-producer", num_ranks=2)
    try:
        done = producers.call_each("produce", [(ch, 0, 300), (ch, 1000, 300)])
        time.sleep(1.0)
        assert ch.qsize(key="k") <= 5, "maxsize still bounds the queue"
        assert not done.done(), "producers must be held back while the channel is full"
        got = [ch.get(key="k") for _ in range(600)]
        assert done.wait(timeout=120) == [300, 300]
        for i in range(20):
            reader.put(i)
        assert [reader.get() for _ in range(20)] == list(range(20))  # prefetched, in order
        for i in range(5):
            reader.put(i, key="stop-early")
        assert reader.get(key="stop-early") == 0  # took all 5; 4 wait in this client's buffer
        assert reader.give_back_prefetched() == 4
        other = Channel.connect(reader.name)  # another consumer finds them, in order
        assert [other.get(key="stop-early", timeout=30) for _ in range(4)] == [1, 2, 3, 4]
        assert Channel.connect(reader.name).prefetch == 8
        reader.close()
        with pytest.raises(ChannelClosed):
            reader.get()
        for lo in (0, 1000):
            mine = [x for x in got if lo <= x < lo + 300]
            assert mine == list(range(lo, lo + 300)), "per-producer FIFO must survive pipelining"
    finally:
        producers.shutdown()
    with pytest.raises(ChannelError, match="pipeline_depth must be >= 0"):
        Channel.create("bad-depth", pipeline_depth=-1)
    with pytest.raises(ChannelError, match="prefetch must be >= 1"):
        Channel.create("bad-prefetch", prefetch=0)


def test_a_cancelled_get_whose_reply_never_comes_still_ends(ray_cluster, monkeypatch):
    """A synchronous get whose call is cancelled is abandoned by the cancel and again by the waiting
    thread (Ray may cancel the first abandon, made inside the cancelled call); then it waits a
    bounded time for the reply, which Ray may never send, not forever."""
    import ray

    from infinirl.runtime import CallCancelled, channel
    from infinirl.runtime.cancellation import CancelToken, run_with_token

    monkeypatch.setattr(channel, "CANCELLED_GET_WAIT_S", 0.5)

    @ray.remote(num_cpus=0)
    class Silent:
        async def never(self):
            await asyncio.sleep(3600)

    silent = Silent.remote()
    token, abandoned, out = CancelToken("test[rank 0].take()"), [], {}

    def take():
        try:
            run_with_token(token, channel._wait_get, (silent.never.remote(), lambda: abandoned.append(True)), {})
        except CallCancelled as exc:
            out["error"] = exc

    thread = threading.Thread(target=take, daemon=True)
    thread.start()
    time.sleep(1.0)
    assert thread.is_alive(), "an uncancelled get waits for its reply"
    token.cancel()
    thread.join(timeout=30)
    assert not thread.is_alive() and abandoned == [True, True]
    assert "test[rank 0].take() was cancelled" in str(out["error"])
    ray.kill(silent)


def test_a_cancelled_wait_without_its_own_cancel_ends_with_call_cancelled(ray_cluster, monkeypatch):
    """A synchronous put waits through ``cancellation.wait_ref`` with no ``on_cancel``: the cancel
    is ``ray.cancel`` of the awaited call, which ends the wait with ``CallCancelled`` even when the
    call itself ignores the cancel (the bounded wait for a lost reply is the get test's above)."""
    import ray

    from infinirl.runtime import CallCancelled, cancellation
    from infinirl.runtime.cancellation import CancelToken, run_with_token

    monkeypatch.setattr(cancellation, "CANCELLED_WAIT_S", 0.5)

    @ray.remote(num_cpus=0)
    class Deaf:
        async def never(self):
            while True:
                try:
                    await asyncio.sleep(3600)
                except asyncio.CancelledError:
                    continue  # ignores the cancel: no reply ever comes

    deaf = Deaf.remote()
    token, out = CancelToken("test[rank 0].put()"), {}

    def put():
        try:
            run_with_token(token, cancellation.wait_ref, (deaf.never.remote(),), {})
        except CallCancelled as exc:
            out["error"] = exc

    thread = threading.Thread(target=put, daemon=True)
    thread.start()
    time.sleep(1.0)
    assert thread.is_alive(), "an uncancelled wait waits for its reply"
    token.cancel()
    thread.join(timeout=30)
    assert not thread.is_alive()
    assert "test[rank 0].put() was cancelled" in str(out["error"])
    ray.kill(deaf)


def test_a_same_process_item_is_served_only_to_its_pid_on_its_node():
    """Process ids repeat across nodes (containers): a same-process item must not reach another
    node's process that happens to have the producer's pid."""
    from infinirl.runtime.channel_actor import _Item
    from infinirl.runtime.transport import Envelope

    item = _Item(Envelope("local", 1234, "node-a", local_id=1), 1.0)
    assert item.serves(1234, "node-a")
    assert not item.serves(1234, "node-b") and not item.serves(99, "node-a")


def test_pipelined_puts_from_two_threads_all_arrive(ray_cluster):
    """Each pipelined put takes the next number of the producer's order: two threads that took the
    same number would leave a later one unused, and every put behind it would wait for it forever."""
    ch = Channel.create(f"pipe-threads-{time.time_ns()}", pipeline_depth=4)
    old_interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible, inside the numbering too
    try:
        threads = [threading.Thread(target=lambda lo=lo: [ch.put(lo + i) for i in range(100)], daemon=True)
                   for lo in (0, 1000)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=30)
    finally:
        sys.setswitchinterval(old_interval)
    assert not any(thread.is_alive() for thread in threads), "a put waits for a turn that never comes"
    got = [ch.get(timeout=10) for _ in range(200)]
    for lo in (0, 1000):
        assert [x for x in got if lo <= x < lo + 100] == list(range(lo, lo + 100))
    ch.destroy()


def test_timeout_zero_takes_what_is_there(ray_cluster):
    ch = fresh(maxsize=2)
    ch.put("a", timeout=0)
    ch.put("b", timeout=0)
    with pytest.raises(TimeoutError, match="put on key"):
        ch.put("c", timeout=0)  # full
    assert ch.get(timeout=0) == "a"
    assert ch.get_batch(1, timeout=0) == ["b"]
    with pytest.raises(TimeoutError, match="get on key"):
        ch.get(timeout=0)  # empty
    ch.destroy()


def test_put_many_and_put_async_keep_the_order_of_pipelined_puts(ray_cluster):
    ch = Channel.create(f"pipe-mixed-{time.time_ns()}", maxsize=1, pipeline_depth=4)
    got: list = []
    consumer = threading.Thread(target=lambda: (time.sleep(0.5), got.extend(ch.get(timeout=30) for _ in range(7))),
                                daemon=True)
    consumer.start()
    for item in "xab":  # x fills the key; a waits for space and b for its turn
        ch.put(item)
    ch.put_many(["c"])
    ch.put("d")
    ch.put("e")
    asyncio.run(ch.put_async("f"))
    ch.flush()
    consumer.join(timeout=30)
    assert got == list("xabcdef")
    ch.destroy()


def test_every_get_serves_the_prefetched_items_first(ray_cluster):
    ch = Channel.create(f"prefetch-order-{time.time_ns()}", prefetch=4)
    for i in range(9):
        ch.put(i, weight=1 + i % 2)
    assert ch.get() == 0  # took 0-3: 1, 2 and 3 wait in this client's buffer
    assert ch.get_batch(3) == [1, 2]
    assert ch.get_with_weight() == (3, 2.0)
    assert asyncio.run(ch.get_async()) == 4
    assert ch.get() == 5  # took 5-8
    assert asyncio.run(ch.get_batch_async(100, timeout=1)) == [6, 7, 8]
    ch.destroy()


def test_create_with_exist_ok_refuses_other_settings(ray_cluster):
    ch = fresh(maxsize=4)
    assert Channel.create(ch.name, maxsize=4, exist_ok=True).info()["maxsize"] == 4
    with pytest.raises(ChannelError, match="maxsize=8.*maxsize=4"):
        Channel.create(ch.name, maxsize=8, exist_ok=True)
    with pytest.raises(ChannelError, match="transport='p2p'.*transport='auto'"):
        Channel.create(ch.name, maxsize=4, transport="p2p", exist_ok=True)
    ch.destroy()


def test_destroy_drops_the_queued_items_this_process_holds(ray_cluster):
    from infinirl.runtime import transport

    ch = fresh()
    ch.register_consumer()
    ch.put("warm-up")  # learns that the only consumer is this process: the next items go by reference
    held = set(transport._local_items)
    ch.put(torch.ones(1 << 16))
    ch.put(torch.ones(1 << 16))
    assert len(set(transport._local_items) - held) == 2
    ch.destroy()
    assert not set(transport._local_items) - held
