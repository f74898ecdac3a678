"""The link's outgoing fair queue: a message on an idle stream goes out within a bounded number of
frames of a backlogged stream, each stream keeps its order, and busy streams share bytes evenly
whatever their frame sizes. Then through a real link: with a backlog of episodes queued, a control
message reaches the wire after a few of them, not after all."""

import json
import socket
import ssl
import threading
from collections import Counter

import pytest

from infinirl.edge.credentials import client_context, server_context
from infinirl.edge.fair_queue import FairQueue
from infinirl.edge.frames import FrameReader, encode_frame
from infinirl.edge.link import PROTOCOL_VERSION, WELCOME, LinkOptions, dial


def drain(queue):
    order = []
    while (item := queue.pop()) is not None:
        order.append(item)
    return order


@pytest.mark.parametrize("bulk_size", [1_000, 64 << 10, 1 << 20])
def test_a_control_message_passes_a_backlog_within_one_turn(bulk_size):
    quantum = 64 << 10
    queue = FairQueue(quantum)
    for index in range(200):
        queue.push("episodes", f"e{index}".encode().ljust(bulk_size, b"."))
    assert queue.pop()[0] == "episodes"  # the backlog's first frame is on the wire
    queue.push("weights.ack", b"w")
    order = drain(queue)
    before = next(i for i, (stream, _) in enumerate(order) if stream == "weights.ack")
    assert before <= max(1, quantum // bulk_size)  # at most one turn of the busy stream
    assert [frame[:5].rstrip(b".") for stream, frame in order if stream == "episodes"] == \
        [f"e{index}".encode() for index in range(1, 200)]  # in order, none lost
    assert queue.bytes == 0 and not queue and queue.pop() is None


def test_busy_streams_share_bytes_evenly_whatever_their_frame_sizes():
    quantum = 4096
    queue = FairQueue(quantum)
    for _ in range(400):
        queue.push("big", b"B" * 50_000)
    for _ in range(40_000):
        queue.push("small", b"s" * 100)
    sent = Counter()
    for _ in range(3000):
        stream, frame = queue.pop()
        sent[stream] += len(frame)
    assert abs(sent["big"] - sent["small"]) <= 50_000 + quantum  # one large frame plus one quantum apart


def test_a_lone_stream_with_frames_larger_than_the_quantum_is_not_held_back():
    queue = FairQueue(16)
    queue.push("weights", b"x" * 10**6)
    assert queue.pop() == ("weights", b"x" * 10**6) and queue.pop() is None


def fake_cloud(listener, context, frames, ready, go):
    """Accept one edge, answer its hello, wait for ``go``, then record the stream of every frame in
    wire order until ``frames`` arrived."""
    raw, _ = listener.accept()
    sock = context.wrap_socket(raw, server_side=True)
    reader = FrameReader()
    while not reader.feed(sock.recv(1 << 16)):
        pass
    sock.sendall(encode_frame(WELCOME, json.dumps({"protocol": PROTOCOL_VERSION}).encode()))
    ready.set()
    go.wait(30)
    order = []
    while len(order) < frames:
        order += [stream for stream, _ in reader.feed(sock.recv(1 << 16))]
    sock.close()
    return order


def test_through_a_link_a_control_message_overtakes_a_queued_backlog(credentials):
    bulk, size = 40, 1 << 20
    results, ready, go = {}, threading.Event(), threading.Event()
    with socket.create_server(("127.0.0.1", 0)) as listener:
        context = server_context(credentials["cloud"])
        context.minimum_version = ssl.TLSVersion.TLSv1_3
        cloud = threading.Thread(target=lambda: results.update(order=fake_cloud(listener, context, bulk + 1, ready,
                                                                               go)), daemon=True)
        cloud.start()
        link = dial(listener.getsockname(), client_context(credentials["edge-0"]),
                    options=LinkOptions(connect_timeout_s=5.0, heartbeat_s=5.0, dead_after_s=60.0))
        try:
            assert ready.wait(10)
            for _ in range(bulk):  # the peer reads nothing yet: all but what TCP's buffers hold stays queued
                link.send("episodes", b"e" * size, timeout=10.0)
            link.send("robot.reply", b"{}", timeout=10.0)
            go.set()
            cloud.join(60)
        finally:
            link.close()
    order = [stream for stream in results["order"] if not stream.startswith("link.")]  # heartbeats
    assert sorted(Counter(order).items()) == [("episodes", bulk), ("robot.reply", 1)]
    assert order.index("robot.reply") < bulk // 4  # first in first out would send it last
