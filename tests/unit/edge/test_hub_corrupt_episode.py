"""An episode the cloud cannot decode is skipped and reported, and the link goes on (the next episodes
arrive, robot calls keep their stream); any other failure of the hub's episode receiver closes the
edge's link with a reason naming it. Nothing ends the receiver silently. Waits are bounded."""

import json
import struct

import pytest

from infinirl.edge import protocol
from infinirl.edge.cloud_hub import CloudHub, HubOptions, wait_for
from infinirl.edge.codec import encode_episode
from infinirl.edge.credentials import client_context
from infinirl.edge.link import LinkOptions, dial
from tests.unit.edge.test_edge_hub import Received, an_episode

LINK = LinkOptions(connect_timeout_s=2.0, heartbeat_s=0.2, dead_after_s=1.0)


@pytest.fixture()
def hub(credentials):
    received = Received()
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=received,
                  options=HubOptions(link=LINK)) as hub:
        hub.received = received
        yield hub


def with_header(header, body=b""):
    encoded = json.dumps(header).encode()
    return b"IEP1" + struct.pack("!I", len(encoded)) + encoded + body


def test_a_corrupt_episode_is_skipped_and_reported_and_the_link_goes_on(hub, credentials):
    good = encode_episode(an_episode(1), episode_id="edge-1-a-1")
    corrupt = [b"not an episode at all",  # wrong magic: ValueError
               good[:-7],  # truncated: the last field does not decompress
               with_header({"id": 5, "fields": []}),  # an id that is no string
               with_header({"id": "edge-1-a-0", "fields": [{"name": "state", "codec": "zlib", "dtype": "<f4",
                                                            "shape": [2], "sizes": [4]}]}, b"\0\0\0\0")]
    link = dial(hub.address, client_context(credentials["edge-1"]), options=LINK)
    try:
        for payload in corrupt:
            link.send(protocol.EPISODES, payload, timeout=5.0)
        link.send(protocol.EPISODES, good, timeout=5.0)
        ack = protocol.load(link.recv(protocol.EPISODE_ACKS, timeout=10.0))
        assert ack == {"ids": ["edge-1-a-1"]} and link.alive
    finally:
        link.close()
    assert list(hub.received.episodes) == ["edge-1-a-1"]
    assert hub.counts["corrupt_episodes"] == len(corrupt) and hub.stats()["episode_errors"] == len(corrupt)
    errors = list(hub.episode_errors)
    assert "ValueError" in errors[0] and "error" in errors[1] and "5" in errors[2]
    assert all("edge-1" in error and "skipped" in error for error in errors)


def test_any_other_failure_of_the_receiver_closes_the_link_naming_it(hub, credentials):
    def broken_take(link, episode_id, episode):
        raise RuntimeError("the hub's delivery is broken")

    hub._take = broken_take  # a failure outside decoding: a bug, or an acknowledgement that cannot be queued
    link = dial(hub.address, client_context(credentials["edge-1"]), options=LINK)
    try:
        assert wait_for(lambda: hub.link("edge-1") is not None, 10.0)
        server_side = hub.link("edge-1")
        link.send(protocol.EPISODES, encode_episode(an_episode(0), episode_id="edge-1-a-0"), timeout=5.0)
        assert wait_for(lambda: not server_side.alive, 10.0)
        assert wait_for(lambda: not link.alive, 10.0)
    finally:
        link.close()
    assert "the hub's delivery is broken" in server_side.closed_reason
    assert "RuntimeError" in server_side.closed_reason
    assert hub.counts["receive_failures"] == 1 and "the hub's delivery is broken" in hub.episode_errors[-1]
    assert hub.link("edge-1") is None
