"""TCP through the link: bytes arrive exactly, several connections at once, a refused target and an
unknown service close the cloud's client, closes travel both ways (half-close included), a large
transfer is exact, and a client that stops reading holds up neither the link's other streams nor
the other connections."""

import hashlib
import os
import socket
import threading

import pytest

from infinirl.edge.cloud_hub import wait_for
from infinirl.edge.credentials import client_context, server_context
from infinirl.edge.emulator import EmulatorSpec, LinkEmulator
from infinirl.edge.link import CloudListener, LinkOptions, dial
from infinirl.edge.tunnel import DATA, TunnelEnd, TunnelListener, TunnelOptions, decode_message, encode_message

LINK = LinkOptions(connect_timeout_s=5.0, heartbeat_s=0.2, dead_after_s=5.0)
TUNNEL = TunnelOptions(connect_timeout_s=2.0, open_timeout_s=5.0, io_timeout_s=30.0)
TIMEOUT = 20.0


class Target:
    """A TCP server at the edge running ``handle(sock)`` per connection on a thread of its own."""

    def __init__(self, handle):
        self.handle, self.accepted = handle, 0
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(0.2)
        self.address = self.server.getsockname()[:2]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        while not self.stop.is_set():
            try:
                sock, _ = self.server.accept()
            except TimeoutError:
                continue
            self.accepted += 1
            sock.settimeout(TIMEOUT)
            threading.Thread(target=self._run, args=(sock,), daemon=True).start()

    def _run(self, sock):
        try:
            self.handle(sock)
        except OSError:
            pass
        finally:
            sock.close()

    def close(self):
        self.stop.set()
        self.thread.join(timeout=2.0)
        self.server.close()


def echo(sock):
    while data := sock.recv(65536):
        sock.sendall(data)


def digest_until_eof(sock):
    """Reads to the client's half-close, then answers the SHA-256 and length of what came."""
    sha, total = hashlib.sha256(), 0
    while data := sock.recv(65536):
        sha.update(data)
        total += len(data)
    sock.sendall(f"{sha.hexdigest()} {total}".encode())


def receive_all(sock):
    chunks = []
    while data := sock.recv(65536):
        chunks.append(data)
    return b"".join(chunks)


@pytest.fixture()
def link_pair(credentials):
    with CloudListener("127.0.0.1", 0, server_context(credentials["cloud"]), options=LINK) as listener:
        result = {}
        thread = threading.Thread(target=lambda: result.update(link=listener.accept(timeout=10.0)), daemon=True)
        thread.start()
        edge = dial(listener.address, client_context(credentials["edge-0"]), options=LINK)
        thread.join()
        cloud = result["link"]
        try:
            yield cloud, edge
        finally:
            edge.close()
            cloud.close()


@pytest.fixture()
def tunnel(link_pair):
    """``make(handle, options)``: a target at the edge, both tunnel ends, the cloud's port."""
    cloud_link, edge_link = link_pair
    made = []

    def make(handle, options=TUNNEL, services=None):
        target = Target(handle)
        edge_end = TunnelEnd(edge_link, targets=services or {"svc": target.address}, options=options).start()
        cloud_end = TunnelEnd(cloud_link, options=options).start()
        listener = TunnelListener(("127.0.0.1", 0), lambda: cloud_end, service="svc").start()
        made.extend([listener, cloud_end, edge_end, target])
        return listener, cloud_end, edge_end, target

    yield make
    for part in made:
        part.close()


def connect(listener):
    sock = socket.create_connection(listener.address, timeout=TIMEOUT)
    sock.settimeout(TIMEOUT)
    return sock


def test_messages_round_trip():
    assert decode_message(encode_message(DATA, 7, b"abc")) == (DATA, 7, b"abc")
    with pytest.raises(ValueError, match="shorter than its 5-byte header"):
        decode_message(b"\x02\x00")


def test_options_are_checked():
    with pytest.raises(ValueError, match="chunk_bytes"):
        TunnelOptions(chunk_bytes=1 << 20, window_bytes=1 << 16)
    with pytest.raises(ValueError, match="io_timeout_s"):
        TunnelOptions(io_timeout_s=0)


def test_concurrent_connections_echo_byte_exact(tunnel):
    listener, cloud_end, edge_end, target = tunnel(echo)
    results, errors = {}, []

    def client(index):
        try:
            payload = os.urandom(200_000 + 1000 * index)
            with connect(listener) as sock:
                sender = threading.Thread(target=sock.sendall, args=(payload,), daemon=True)
                sender.start()  # both ways at once: the echo must not wait for the whole upload
                got = bytearray()
                while len(got) < len(payload):
                    data = sock.recv(65536)
                    assert data, "the tunnel closed before the echo was complete"
                    got += data
                sender.join(TIMEOUT)
                results[index] = bytes(got) == payload
        except Exception as exc:  # reported by the assertion below
            errors.append(repr(exc))

    threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(TIMEOUT * 2)
    assert not errors and results == dict.fromkeys(range(6), True)
    assert target.accepted == 6
    assert wait_for(lambda: cloud_end.connections() == 0 and edge_end.connections() == 0, TIMEOUT)
    assert cloud_end.counts["finished"] == edge_end.counts["finished"] == 6
    assert not cloud_end.failures and not edge_end.failures


def test_large_upload_with_half_close_then_answer(tunnel):
    listener, cloud_end, edge_end, _ = tunnel(digest_until_eof)
    payload = os.urandom(8 << 20)
    with connect(listener) as sock:
        sock.sendall(payload)
        sock.shutdown(socket.SHUT_WR)  # the target sees the end of the upload, and can still answer
        answer = receive_all(sock).decode()
    assert answer == f"{hashlib.sha256(payload).hexdigest()} {len(payload)}"
    assert wait_for(lambda: cloud_end.connections() == 0 and edge_end.connections() == 0, TIMEOUT)
    assert cloud_end.counts["bytes_out"] == edge_end.counts["bytes_in"] == len(payload)


def test_large_download_then_target_closes(tunnel):
    payload = os.urandom(8 << 20)
    listener, cloud_end, edge_end, _ = tunnel(lambda sock: sock.sendall(payload))
    with connect(listener) as sock:
        assert receive_all(sock) == payload  # the target's close reaches the client as the end
    assert wait_for(lambda: cloud_end.connections() == 0 and edge_end.connections() == 0, TIMEOUT)
    assert not cloud_end.failures and not edge_end.failures


def test_a_refused_target_closes_the_client_and_says_why(tunnel):
    closed_port = socket.create_server(("127.0.0.1", 0))
    address = closed_port.getsockname()[:2]
    closed_port.close()  # nothing listens there any more
    listener, cloud_end, edge_end, _ = tunnel(echo, services={"svc": address})
    with connect(listener) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\n\r\n")
        assert receive_all(sock) == b""
    assert wait_for(lambda: cloud_end.failures, TIMEOUT)
    assert "unreachable from the edge" in cloud_end.failures[0] and f"{address[1]}" in cloud_end.failures[0]
    assert cloud_end.connections() == 0 and edge_end.connections() == 0


def test_an_unknown_service_is_refused_and_nothing_is_reached(tunnel):
    listener, cloud_end, edge_end, target = tunnel(echo, services={"other": ("127.0.0.1", 1)})
    with connect(listener) as sock:
        assert receive_all(sock) == b""
    assert wait_for(lambda: cloud_end.failures, TIMEOUT)
    assert "no tunnel service 'svc'" in cloud_end.failures[0] and "other" in cloud_end.failures[0]
    assert target.accepted == 0


def test_the_client_closing_reaches_the_target(tunnel):
    seen = {}

    def wait_for_eof(sock):
        seen["data"] = receive_all(sock)  # returns at the client's close

    listener, cloud_end, edge_end, _ = tunnel(wait_for_eof)
    with connect(listener) as sock:
        sock.sendall(b"bye")
    assert wait_for(lambda: "data" in seen, TIMEOUT) and seen["data"] == b"bye"
    assert wait_for(lambda: cloud_end.connections() == 0 and edge_end.connections() == 0, TIMEOUT)


def test_the_link_closing_closes_every_connection(tunnel, link_pair):
    listener, cloud_end, edge_end, _ = tunnel(echo)
    socks = [connect(listener) for _ in range(3)]
    for sock in socks:
        sock.sendall(b"x")
        assert sock.recv(1) == b"x"
    link_pair[1].close("cable pulled")
    for sock in socks:
        try:
            assert sock.recv(1) == b""
        except ConnectionResetError:
            pass  # a reset is as good an end as a close
        sock.close()
    assert wait_for(lambda: cloud_end.connections() == 0, TIMEOUT)
    assert any("closed" in reason for reason in cloud_end.failures)
    assert not cloud_end.alive


def test_a_client_that_stops_reading_holds_up_neither_other_streams_nor_connections(tunnel, link_pair):
    cloud_link, edge_link = link_pair
    flood = os.urandom(1 << 20)

    def send_forever(sock):
        while True:
            sock.sendall(flood)

    listener, cloud_end, edge_end, _ = tunnel(send_forever)
    echo_target = Target(echo)
    edge_end.targets["echo"] = echo_target.address
    other = TunnelListener(("127.0.0.1", 0), lambda: cloud_end, service="echo").start()
    buffered = []
    try:
        with connect(listener) as stuck:
            assert stuck.recv(1)  # the flood started; from now on this client reads nothing
            # the socket's buffers fill, then the connection's buffer at the cloud fills up to its window, less
            # the chunk being written and the credit not yet returned (returned a quarter window at a time)
            assert wait_for(lambda: cloud_end.buffered_bytes() >= TUNNEL.window_bytes // 2, TIMEOUT)
            for index in range(50):
                edge_link.send("episodes", b"e%d" % index, timeout=5.0)
                buffered.append(cloud_end.buffered_bytes())
            assert [cloud_link.recv("episodes", timeout=5.0) for _ in range(50)] == [b"e%d" % i for i in range(50)]
            with connect(other) as sock:
                sock.sendall(b"still here")
                assert sock.recv(100) == b"still here"
                buffered.append(cloud_end.buffered_bytes())
            assert wait_for(lambda: cloud_end.connections() == 1, TIMEOUT)  # the stuck one stays open
            buffered.append(cloud_end.buffered_bytes())
        assert max(buffered) <= TUNNEL.window_bytes  # a slow reader costs the cloud one window, no more
    finally:
        other.close()
        echo_target.close()


def test_a_client_that_reads_nothing_for_io_timeout_is_closed_with_the_reason(tunnel):
    flood = os.urandom(1 << 20)

    def send_forever(sock):
        while True:
            sock.sendall(flood)

    listener, cloud_end, edge_end, _ = tunnel(send_forever, options=TunnelOptions(io_timeout_s=1.0))
    with connect(listener) as stuck:
        assert stuck.recv(1)
        assert wait_for(lambda: cloud_end.failures, TIMEOUT)
        assert "writing to the connection failed" in cloud_end.failures[0]
        assert wait_for(lambda: cloud_end.connections() == 0 and edge_end.connections() == 0, TIMEOUT)
        assert any("writing to the connection failed" in reason for reason in edge_end.failures)  # told why


def test_episodes_go_up_while_a_download_fills_the_emulated_link(credentials):
    """Page downloads and episodes travel the same way (edge to cloud); an episode sent during a
    download that saturates the link arrives before the download ends."""
    payload = os.urandom(6 << 20)
    target = Target(lambda sock: sock.sendall(payload))
    with CloudListener("127.0.0.1", 0, server_context(credentials["cloud"]), options=LINK) as listener, \
            LinkEmulator(EmulatorSpec.from_rtt(rtt_ms=60, mbit_per_s=20), listener.address) as emulator:
        result = {}
        thread = threading.Thread(target=lambda: result.update(link=listener.accept(timeout=10.0)), daemon=True)
        thread.start()
        edge_link = dial(emulator.address, client_context(credentials["edge-0"]), options=LINK)
        thread.join()
        cloud_link = result["link"]
        edge_end = TunnelEnd(edge_link, targets={"svc": target.address}, options=TUNNEL).start()
        cloud_end = TunnelEnd(cloud_link, options=TUNNEL).start()
        listener_page = TunnelListener(("127.0.0.1", 0), lambda: cloud_end, service="svc").start()
        received = bytearray()
        try:
            with connect(listener_page) as sock:
                def download():
                    while data := sock.recv(65536):
                        received.extend(data)

                reader = threading.Thread(target=download, daemon=True)
                reader.start()
                assert wait_for(lambda: len(received) >= 1 << 20, TIMEOUT)
                episode = os.urandom(200_000)
                edge_link.send("episodes", episode, timeout=TIMEOUT)
                assert cloud_link.recv("episodes", timeout=TIMEOUT) == episode
                assert len(received) < len(payload)  # the download was still running
                reader.join(TIMEOUT * 2)
            assert bytes(received) == payload
        finally:
            for part in (listener_page, cloud_end, edge_end, edge_link, cloud_link, target):
                part.close()


@pytest.mark.parametrize(("cloud_limit", "edge_limit", "reason"), [
    (1, 4, "1 tunnel connections are open to edge-0 already"),
    (4, 1, "the edge has 1 tunnel connections open"),
])
def test_connections_beyond_the_limit_are_closed_with_the_reason(link_pair, cloud_limit, edge_limit, reason):
    cloud_link, edge_link = link_pair
    target = Target(echo)
    edge_end = TunnelEnd(edge_link, targets={"svc": target.address},
                         options=TunnelOptions(max_connections=edge_limit, connect_timeout_s=2.0)).start()
    cloud_end = TunnelEnd(cloud_link, options=TunnelOptions(max_connections=cloud_limit, open_timeout_s=5.0)).start()
    listener = TunnelListener(("127.0.0.1", 0), lambda: cloud_end, service="svc").start()
    try:
        with connect(listener) as first:
            first.sendall(b"a")
            assert first.recv(1) == b"a"
            with connect(listener) as second:
                assert receive_all(second) == b""
            assert wait_for(lambda: cloud_end.failures, TIMEOUT) and reason in cloud_end.failures[0]
            first.sendall(b"b")
            assert first.recv(1) == b"b"  # the open connection did not notice
        assert target.accepted == 1
    finally:
        for part in (listener, cloud_end, edge_end, target):
            part.close()
