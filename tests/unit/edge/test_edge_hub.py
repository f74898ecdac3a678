"""Edge client and cloud hub over the emulated link (60 ms RTT, 20 Mbit/s): episodes arrive once
each across a link cut mid-stream, weights go down as deltas and continue after a reconnect, a
delta against a base the edge does not hold is refused and replaced by a full push, wrong
credentials stop the edge with a clear error and deliver nothing."""

import dataclasses
import threading
import time

import numpy as np
import pytest

from infinirl.edge import protocol
from infinirl.edge.cloud_hub import CloudHub, HubOptions, wait_for
from infinirl.edge.codec import FrameOptions, HeldWeights, encode_episode
from infinirl.edge.credentials import TlsFiles, client_context, server_context
from infinirl.edge.edge_client import EdgeClient, EdgeOptions
from infinirl.edge.emulator import EmulatorSpec, LinkEmulator
from infinirl.edge.link import CloudListener, Link, LinkAuthError, LinkOptions, dial
from infinirl.edge.spool import EpisodeSpool, EpisodeTooLargeError

LINK = LinkOptions(connect_timeout_s=2.0, heartbeat_s=0.2, dead_after_s=1.0)
EDGE = EdgeOptions(reconnect_min_s=0.1, reconnect_max_s=0.5, link=LINK)


def an_episode(index, steps=20):
    rng = np.random.default_rng(index)
    return {"state": rng.normal(size=(steps + 1, 9)).astype(np.float32),
            "pixels.corner": rng.integers(0, 255, (steps + 1, 32, 32, 3), dtype=np.uint8),
            "action": rng.uniform(-1, 1, (steps, 4)).astype(np.float32),
            "reward": np.full(steps, float(index), np.float32)}


class Received:
    def __init__(self):
        self.episodes, self.lock = {}, threading.Lock()

    def __call__(self, edge, episode_id, episode):
        with self.lock:
            assert episode_id not in self.episodes
            self.episodes[episode_id] = (edge, episode)


@pytest.fixture()
def cloud(credentials):
    received = Received()
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=received,
                  options=HubOptions(link=LINK)) as hub:
        with LinkEmulator(EmulatorSpec.from_rtt(rtt_ms=60, mbit_per_s=20), hub.address) as emulator:
            yield hub, emulator, received


def test_a_cut_mid_stream_loses_nothing_and_duplicates_nothing(cloud, credentials, tmp_path):
    hub, emulator, received = cloud
    client = EdgeClient(emulator.address, credentials["edge-0"], name="edge-0", spool=EpisodeSpool(tmp_path),
                        frames=FrameOptions(format="png"), options=EDGE).start()
    try:
        ids = [client.submit(an_episode(i)) for i in range(3)]
        assert client.wait_drained(30.0)
        emulator.cut()  # mid-stream: the next episodes are sent into a dead link
        ids += [client.submit(an_episode(i)) for i in range(3, 6)]
        assert wait_for(lambda: not client.connected, 10.0)
        assert client.offline_s() > 0 and len(client.spool) >= 1
        emulator.restore()
        assert client.wait_drained(30.0)
    finally:
        client.close()
    assert sorted(received.episodes) == sorted(ids)
    for index, episode_id in enumerate(ids):
        edge, episode = received.episodes[episode_id]
        assert edge == "edge-0"
        for name, array in an_episode(index).items():
            assert np.array_equal(episode[name], array)  # PNG: lossless
    assert client.counts["disconnects"] >= 1 and client.counts["connects"] >= 2
    assert not list(tmp_path.glob("*.episode"))


def test_the_hub_delivers_a_resent_episode_once(cloud, credentials):
    hub, _, received = cloud
    link = dial(hub.address, client_context(credentials["edge-1"]), options=LINK)
    try:
        payload = encode_episode(an_episode(0), episode_id="edge-1-a-0")
        for _ in range(2):
            link.send(protocol.EPISODES, payload, timeout=5.0)
        acks = [protocol.load(link.recv(protocol.EPISODE_ACKS, timeout=10.0)) for _ in range(2)]
    finally:
        link.close()
    assert acks == [{"ids": ["edge-1-a-0"]}] * 2
    assert list(received.episodes) == ["edge-1-a-0"] and hub.counts["duplicates"] == 1


def test_an_episode_the_cloud_could_not_take_is_resent_on_the_next_link(credentials):
    """``on_episode`` failing (e.g. the learner's channel timing out) closes the edge's link
    without acknowledging the episode; the edge reconnects and resends it, and it arrives once."""
    taken, failures = [], []

    def on_episode(edge, episode_id, episode):
        if not failures:
            failures.append(episode_id)
            raise TimeoutError("the learner's channel is full")
        taken.append(episode_id)

    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=on_episode,
                  options=HubOptions(link=LINK)) as hub:
        client = EdgeClient(hub.address, credentials["edge-0"], name="edge-0", options=EDGE).start()
        try:
            ids = [client.submit(an_episode(i)) for i in range(2)]
            assert client.wait_drained(30.0)
        finally:
            client.close()
    assert failures == ids[:1] and sorted(taken) == sorted(ids)
    assert hub.counts["delivery_failures"] == 1 and client.counts["connects"] >= 2


def test_an_edge_cannot_send_episodes_in_another_edges_name(cloud, credentials):
    hub, _, received = cloud
    link = dial(hub.address, client_context(credentials["edge-1"]), options=LINK)
    link.send(protocol.EPISODES, encode_episode(an_episode(0), episode_id="edge-0-a-0"), timeout=5.0)
    assert wait_for(lambda: not link.alive, 10.0)
    assert received.episodes == {} and hub.counts["foreign_ids"] == 1


def weights(step):
    rng = np.random.default_rng(0)
    return {"w": (rng.normal(0, 0.1, (128, 64)) + 1e-3 * step).astype(np.float32),
            "b": np.full(64, 0.01 * step, np.float32)}


def test_weights_go_down_as_deltas_across_a_reconnect_and_a_wrong_base_gets_a_full_push(cloud, credentials):
    hub, emulator, _ = cloud
    client = EdgeClient(emulator.address, credentials["edge-0"], name="edge-0", options=EDGE).start()
    try:
        hub.publish(weights(1), 1)
        assert client.wait_weights(1, 20.0)
        hub.publish(weights(2), 2)
        assert client.wait_weights(2, 20.0)
        assert hub.counts["weight_pushes_full"] == 1 and hub.counts["weight_pushes_delta"] == 1
        emulator.cut("reset")
        assert wait_for(lambda: not client.connected, 10.0)
        assert client.policy_usable(max_offline_s=60.0) and not client.policy_usable(max_offline_s=0.0)
        emulator.restore()
        assert wait_for(lambda: client.connected, 20.0)
        hub.publish(weights(3), 3)
        assert client.wait_weights(3, 20.0)
        assert hub.counts["weight_pushes_delta"] == 2  # the reconnected edge held version 2: still a delta
        held = client.weights
        client.weights = HeldWeights.of(held.version, {n: a + 1.0 for n, a in held.tensors.items()})  # not v3's bits
        hub.publish(weights(4), 4)
        assert client.wait_weights(4, 20.0)
        assert client.counts["weights_refused"] == 1 and hub.counts["weight_pushes_full"] == 2, hub.counts
        for name, array in weights(4).items():
            assert np.array_equal(client.weights.tensors[name], array)  # a full push is exact
    finally:
        client.close()


def test_wrong_credentials_stop_the_edge_and_deliver_nothing(cloud, credentials):
    hub, emulator, received = cloud
    with pytest.raises(ValueError, match="differs from the name in its certificate"):
        EdgeClient(emulator.address, credentials["edge-1"], name="edge-0", options=EDGE)
    impostor = TlsFiles(ca=credentials["edge-0"].ca, cert=credentials["foreign"].cert, key=credentials["foreign"].key)
    client = EdgeClient(emulator.address, impostor, name="edge-0", options=EDGE).start()
    try:
        client.spool.put("edge-0-x-0", encode_episode(an_episode(0), episode_id="edge-0-x-0"))
        assert wait_for(lambda: client.error is not None, 20.0)
        with pytest.raises(LinkAuthError, match="refused this edge's certificate"):
            client.submit(an_episode(1))
    finally:
        client.close()
    assert wait_for(lambda: len(hub.refusals) == 1, 10.0)
    assert "CERTIFICATE_VERIFY_FAILED" in hub.refusals[0] and received.episodes == {}


def test_a_client_that_never_speaks_does_not_hold_up_other_edges(credentials):
    import socket

    patient = LinkOptions(connect_timeout_s=60.0, heartbeat_s=0.2, dead_after_s=1.0)
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=Received(),
                  options=HubOptions(link=patient)) as hub:
        silent = socket.create_connection(hub.address)  # TCP only: its handshake waits up to 60 s
        client = EdgeClient(hub.address, credentials["edge-0"], name="edge-0", options=EDGE).start()
        try:
            assert client.wait_connected(20.0)
        finally:
            client.close()
            silent.close()


def test_with_commit_acks_an_episode_is_acknowledged_once_committed(credentials):
    """``commit_acks``: delivery alone acknowledges nothing; :meth:`CloudHub.commit` does, on the
    edge's present link; a resend of a delivered, uncommitted id is delivered again (the owner's
    commit report may have been lost) and acknowledged only by the commit; one of a committed id is
    acknowledged at once and not delivered."""
    delivered = []
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=lambda *args: delivered.append(args[1]),
                  options=HubOptions(link=LINK), commit_acks=True) as hub:
        link = dial(hub.address, client_context(credentials["edge-1"]), options=LINK)
        try:
            payload = encode_episode(an_episode(0), episode_id="edge-1-a-0")
            link.send(protocol.EPISODES, payload, timeout=5.0)
            assert wait_for(lambda: delivered == ["edge-1-a-0"], 10.0)
            link.send(protocol.EPISODES, payload, timeout=5.0)  # resent before its commit
            assert wait_for(lambda: delivered == ["edge-1-a-0"] * 2, 10.0)
            with pytest.raises(TimeoutError):
                link.recv(protocol.EPISODE_ACKS, timeout=0.5)
            assert hub.commit(["edge-1-a-0"]) == 1
            assert protocol.load(link.recv(protocol.EPISODE_ACKS, timeout=10.0)) == {"ids": ["edge-1-a-0"]}
            link.send(protocol.EPISODES, payload, timeout=5.0)  # resent after its commit (the ack was lost)
            assert protocol.load(link.recv(protocol.EPISODE_ACKS, timeout=10.0)) == {"ids": ["edge-1-a-0"]}
        finally:
            link.close()
    assert delivered == ["edge-1-a-0"] * 2 and hub.counts["duplicates"] == 2 and hub.counts["redelivered"] == 1


def test_an_episode_whose_commit_report_was_lost_is_delivered_again_and_acknowledged(credentials):
    """The learner committed the episode but its report never reached the hub: the edge's resend on
    its next link is delivered again, the owner recognises it and reports it again, and the edge's
    spool drains, instead of the episode holding one of the edge's in-flight slots for good."""
    stored, hub_of = {}, {}

    def on_episode(edge, episode_id, episode):
        first = episode_id not in stored
        stored.setdefault(episode_id, episode)  # the store keeps each source id once
        if not first:  # the first report was lost; this one arrives (from another thread, as the learner's)
            threading.Thread(target=hub_of["hub"].commit, args=([episode_id],), daemon=True).start()

    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=on_episode, options=HubOptions(link=LINK),
                  commit_acks=True) as hub:
        hub_of["hub"] = hub
        client = EdgeClient(hub.address, credentials["edge-0"], name="edge-0", options=EDGE).start()
        try:
            episode_id = client.submit(an_episode(0))
            assert wait_for(lambda: episode_id in stored, 20.0)
            assert not client.wait_drained(0.5)
            hub.link("edge-0").close("dropped by the test")
            assert client.wait_drained(30.0)
        finally:
            client.close()
    assert list(stored) == [episode_id] and hub.counts["redelivered"] == 1


def test_an_acknowledgement_racing_the_send_frees_its_window_slot(credentials, monkeypatch):
    """With a window of one, an acknowledgement processed before ``link.send`` returned must still
    free the slot, or the next episode would never be sent on this link."""
    real_send = Link.send

    def slow_episode_send(self, stream, payload, timeout):
        real_send(self, stream, payload, timeout)
        if stream == protocol.EPISODES:
            time.sleep(0.5)  # the hub stores and acknowledges meanwhile

    monkeypatch.setattr(Link, "send", slow_episode_send)
    received = Received()
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=received, options=HubOptions(link=LINK)) as hub:
        client = EdgeClient(hub.address, credentials["edge-0"], name="edge-0",
                            options=dataclasses.replace(EDGE, window=1)).start()
        try:
            ids = [client.submit(an_episode(i, steps=2)) for i in range(3)]
            assert client.wait_drained(30.0)
        finally:
            client.close()
    assert sorted(received.episodes) == sorted(ids) and client.counts["connects"] == 1


def test_a_failure_in_the_clients_thread_is_raised_by_check_not_hidden(credentials, tmp_path):
    """A disk error while sending is retried on a new link; any other failure ends the client's
    thread, and ``check()`` (so ``submit`` and the waits) raises it instead of the edge waiting on a
    thread that is gone."""
    received = Received()
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=received, options=HubOptions(link=LINK)) as hub:
        spool = EpisodeSpool(tmp_path)
        client = EdgeClient(hub.address, credentials["edge-0"], name="edge-0", spool=spool, options=EDGE)
        real_read, failures = spool.read, [OSError(5, "Input/output error")]

        def failing_read(episode_id):
            if failures:
                raise failures.pop()
            return real_read(episode_id)

        spool.read = failing_read
        client.start()
        try:
            first = client.submit(an_episode(0))
            assert client.wait_drained(30.0)
            assert client.counts["session_failures"] == 1 and client.error is None
            failures.append(RuntimeError("a bug"))
            client.submit(an_episode(1))
            assert wait_for(lambda: client.error is not None, 20.0)
            with pytest.raises(RuntimeError, match="the link's thread failed .*a bug"):
                client.wait_drained(5.0)
            with pytest.raises(RuntimeError, match="a bug"):
                client.submit(an_episode(2))
        finally:
            client.close()
    assert list(received.episodes) == [first]


def test_an_episode_too_large_for_a_frame_is_refused_at_submit(credentials, monkeypatch):
    monkeypatch.setattr("infinirl.edge.spool.MAX_PAYLOAD_BYTES", 1000)
    client = EdgeClient(("127.0.0.1", 1), credentials["edge-0"], name="edge-0", options=EDGE)
    with pytest.raises(EpisodeTooLargeError, match="more than a frame of the link carries"):
        client.submit(an_episode(0))
    assert len(client.spool) == 0


def test_a_malformed_acknowledgement_closes_the_link_and_the_edge_reconnects(credentials):
    """A bad ``episodes.ack`` must not kill the edge's receiver while the link lives (the window
    would fill and sending stop for good): the link closes with the reason, the next one works."""
    with CloudListener("127.0.0.1", 0, server_context(credentials["cloud"]), options=LINK) as listener:
        client = EdgeClient(listener.address, credentials["edge-0"], name="edge-0", options=EDGE).start()
        try:
            for bad in (b"[1]", b'{"ids": [["edge-0-x"]]}'):
                link = listener.accept(timeout=20.0)
                link.send(protocol.EPISODE_ACKS, bad, timeout=5.0)
                assert wait_for(lambda: not link.alive, 10.0)  # noqa: B023
                assert "acknowledgement receiver failed" in link.closed_reason or not client.connected
            assert listener.accept(timeout=20.0).alive
            assert client.counts["receive_failures"] == 2 and client.error is None
        finally:
            client.close()


def test_a_malformed_weights_acknowledgement_closes_that_edges_link(cloud, credentials):
    hub, _, _ = cloud
    hub.publish(weights(1), 1)
    link = dial(hub.address, client_context(credentials["edge-1"]), options=LINK)
    try:
        link.recv(protocol.WEIGHTS, timeout=10.0)
        link.send(protocol.WEIGHT_ACKS, b'["not", "an", "object"]', timeout=5.0)
        assert wait_for(lambda: not link.alive, 10.0)
        assert hub.counts["receive_failures"] == 1
    finally:
        link.close()
