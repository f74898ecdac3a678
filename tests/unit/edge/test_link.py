"""The link: mutual TLS refuses wrong credentials on both ends before any frame flows; named
streams share one connection both ways; every call has a timeout; a silent outage closes it."""

import socket
import threading
import time

import pytest

from infinirl.edge.credentials import CLOUD_NAME, TlsFiles, client_context, server_context
from infinirl.edge.emulator import EmulatorSpec, LinkEmulator
from infinirl.edge.frames import FrameReader, encode_frame
from infinirl.edge.link import (
    HELLO,
    REFUSED,
    CloudListener,
    LinkAuthError,
    LinkClosedError,
    LinkError,
    LinkOptions,
    dial,
)

FAST = LinkOptions(connect_timeout_s=5.0, heartbeat_s=0.2, dead_after_s=5.0)
QUICK_TO_DIE = LinkOptions(connect_timeout_s=5.0, heartbeat_s=0.2, dead_after_s=1.0)


def accept_in_background(listener):
    result = {}

    def accept():
        try:
            result["link"] = listener.accept(timeout=10.0)
        except Exception as exc:  # the test inspects it
            result["error"] = exc

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    return thread, result


@pytest.fixture()
def listener(credentials):
    with CloudListener("127.0.0.1", 0, server_context(credentials["cloud"]), options=FAST) as cloud:
        yield cloud


def test_streams_multiplex_both_ways(listener, credentials):
    thread, result = accept_in_background(listener)
    edge = dial(listener.address, client_context(credentials["edge-0"]), options=FAST, hello={"weights_version": 3})
    thread.join()
    cloud = result["link"]
    try:
        assert cloud.peer == "edge-0" and cloud.peer_hello["weights_version"] == 3 and edge.peer == "infinirl-cloud"
        big = bytes(range(256)) * 20_000
        edge.send("episodes", big, timeout=5.0)
        edge.send("http", b"GET /", timeout=5.0)
        cloud.send("weights", b"w1", timeout=5.0)
        assert cloud.recv("http", timeout=5.0) == b"GET /"  # not stuck behind the big frame's stream
        assert cloud.recv("episodes", timeout=5.0) == big
        assert edge.recv("weights", timeout=5.0) == b"w1"
        with pytest.raises(TimeoutError, match="nothing on stream 'weights'"):
            edge.recv("weights", timeout=0.2)
    finally:
        edge.close()
    with pytest.raises(LinkClosedError, match="closed"):
        cloud.recv("episodes", timeout=5.0)


def refused(listener, context):
    thread, result = accept_in_background(listener)
    with pytest.raises(LinkAuthError) as edge_error:
        dial(listener.address, context, options=FAST, hello={"secret": "must not arrive"})
    thread.join()
    assert "link" not in result  # the cloud never got a link, so no frame reached a service
    assert isinstance(result["error"], LinkAuthError)
    for error in (str(edge_error.value), str(result["error"])):
        assert "\n" not in error
    return str(edge_error.value), str(result["error"])


def test_an_edge_certificate_of_another_ca_is_refused_on_both_ends(listener, credentials):
    impostor = TlsFiles(ca=credentials["edge-0"].ca, cert=credentials["foreign"].cert, key=credentials["foreign"].key)
    edge_error, cloud_error = refused(listener, client_context(impostor))
    assert "refused this edge's certificate" in edge_error
    assert "refused" in cloud_error and "CERTIFICATE_VERIFY_FAILED" in cloud_error


def test_an_edge_without_a_certificate_is_refused(listener, credentials):
    import ssl

    context = ssl.create_default_context(cafile=credentials["edge-0"].ca)
    context.check_hostname = False
    edge_error, cloud_error = refused(listener, context)
    assert "refused this edge" in edge_error and "PEER_DID_NOT_RETURN_A_CERTIFICATE" in cloud_error


def test_an_impostor_cloud_is_refused_by_the_edge(credentials):
    foreign_cloud = TlsFiles(ca=credentials["foreign"].ca, cert=credentials["foreign"].cert,
                             key=credentials["foreign"].key)
    with CloudListener("127.0.0.1", 0, server_context(foreign_cloud), options=FAST) as impostor:
        thread, result = accept_in_background(impostor)
        with pytest.raises(LinkAuthError, match="does not verify against this edge's CA"):
            dial(impostor.address, client_context(credentials["edge-0"]), options=FAST)
        thread.join()
        assert "link" not in result


def test_connecting_to_a_silent_port_times_out(credentials):
    server = socket.create_server(("127.0.0.1", 0))  # accepts TCP, never speaks TLS
    try:
        with pytest.raises((TimeoutError, OSError)):
            dial(server.getsockname(), client_context(credentials["edge-0"]),
                 options=LinkOptions(connect_timeout_s=0.5, heartbeat_s=0.1, dead_after_s=1.0))
    finally:
        server.close()


def test_a_connection_dropped_during_the_handshake_is_retryable_not_a_refusal(credentials):
    """A proxy or NAT that accepts and closes at once (the emulator while its link is reset) is an
    outage: the edge retries it, while a refusal (a TLS alert) stops the edge for good."""
    server = socket.create_server(("127.0.0.1", 0))
    closer = threading.Thread(target=lambda: server.accept()[0].close(), daemon=True)
    closer.start()
    try:
        with pytest.raises(LinkError) as error:
            dial(server.getsockname(), client_context(credentials["edge-0"]), options=FAST)
        assert not isinstance(error.value, LinkAuthError) and "closed the connection" in str(error.value)
    finally:
        closer.join(5)
        server.close()


def test_a_connection_dropped_during_the_hello_is_retryable_not_a_refusal(credentials):
    """A cloud that completes the TLS handshake (this edge's certificate verified) and then closes
    without a word, as one restarting does: an outage to retry, not a refusal that stops the edge."""
    server = socket.create_server(("127.0.0.1", 0))
    context = server_context(credentials["cloud"])

    def accept_then_close():
        raw, _ = server.accept()
        raw.settimeout(5.0)
        context.wrap_socket(raw, server_side=True).close()

    closer = threading.Thread(target=accept_then_close, daemon=True)
    closer.start()
    try:
        with pytest.raises(LinkError) as error:
            dial(server.getsockname(), client_context(credentials["edge-0"]), options=FAST)
        assert not isinstance(error.value, LinkAuthError) and "during the hello" in str(error.value)
    finally:
        closer.join(5)
        server.close()


def test_a_hello_the_cloud_refuses_is_a_refusal_at_the_edge(listener, credentials):
    """The cloud says why it refuses a hello (here: another protocol version), so the edge tells it
    from a connection that dropped and does not retry it."""
    thread, result = accept_in_background(listener)
    with pytest.raises(LinkAuthError, match="refused this edge: .*speaks edge link protocol 99"):
        dial(listener.address, client_context(credentials["edge-0"]), options=FAST, hello={"protocol": 99})
    thread.join()
    assert isinstance(result["error"], LinkAuthError) and "link" not in result


def test_a_hello_that_is_not_a_json_object_is_refused_and_closed(listener, credentials):
    thread, result = accept_in_background(listener)
    raw = socket.create_connection(listener.address, timeout=5.0)
    with client_context(credentials["edge-0"]).wrap_socket(raw, server_hostname=CLOUD_NAME) as sock:
        sock.sendall(encode_frame(HELLO, b"[1, 2]"))
        reader, frames = FrameReader(), []
        while not frames:
            data = sock.recv(65536)
            assert data, "closed without saying why"
            frames = reader.feed(data)
        assert frames[0][0] == REFUSED and b"not a JSON object" in frames[0][1]
        assert sock.recv(65536) == b""  # and closed
    thread.join()
    assert isinstance(result["error"], LinkAuthError) and "not a JSON object" in str(result["error"])


def test_a_full_inbox_does_not_spin_the_links_thread(credentials):
    """While a stream's inbox is full the link stops reading (the peer's bytes wait in TCP's window):
    its I/O thread then waits for the consumer instead of selecting on a socket that stays readable."""
    options = LinkOptions(connect_timeout_s=5.0, heartbeat_s=0.2, dead_after_s=30.0, max_queued_frames=2)
    with CloudListener("127.0.0.1", 0, server_context(credentials["cloud"]), options=options) as listener:
        thread, result = accept_in_background(listener)
        edge = dial(listener.address, client_context(credentials["edge-0"]), options=options)
        thread.join()
        cloud = result["link"]
        try:
            frames = [bytes([index]) * (1 << 16) for index in range(12)]
            for frame in frames:
                edge.send("s", frame, timeout=5.0)
            edge.flush(timeout=10.0)  # on the wire: the cloud's socket has bytes its full inbox cannot take
            clock = time.pthread_getcpuclockid(cloud._thread.ident)
            before = time.clock_gettime(clock)
            time.sleep(1.5)
            spent = time.clock_gettime(clock) - before
            assert spent < 0.3, f"the stalled link's thread used {spent:.2f} s of CPU in 1.5 s"
            assert [cloud.recv("s", timeout=10.0) for _ in frames] == frames  # taking frees it: all arrive
            assert cloud.alive and edge.alive
        finally:
            edge.close()
            cloud.close()


def test_a_silent_outage_closes_the_link_on_both_ends(credentials):
    with CloudListener("127.0.0.1", 0, server_context(credentials["cloud"]), options=QUICK_TO_DIE) as listener, \
            LinkEmulator(EmulatorSpec(latency_s=0.005), listener.address) as emulator:
        thread, result = accept_in_background(listener)
        edge = dial(emulator.address, client_context(credentials["edge-0"]), options=QUICK_TO_DIE)
        thread.join()
        cloud = result["link"]
        edge.send("s", b"before", timeout=1.0)
        assert cloud.recv("s", timeout=5.0) == b"before"
        emulator.cut()  # no reset reaches either end: only the missing heartbeats tell
        with pytest.raises(LinkClosedError, match="nothing received"):
            edge.recv("s", timeout=10.0)
        with pytest.raises(LinkClosedError, match="nothing received"):
            cloud.recv("s", timeout=10.0)
        with pytest.raises(LinkClosedError):
            edge.send("s", b"after", timeout=1.0)


def test_send_times_out_when_the_outgoing_buffer_stays_full(listener, credentials):
    options = LinkOptions(connect_timeout_s=5.0, heartbeat_s=0.2, dead_after_s=30.0, max_outgoing_bytes=1 << 20)
    with LinkEmulator(EmulatorSpec(), listener.address) as emulator:
        thread, result = accept_in_background(listener)
        edge = dial(emulator.address, client_context(credentials["edge-0"]), options=options)
        thread.join()
        try:
            emulator.cut()
            with pytest.raises(TimeoutError, match="could not queue"):
                for _ in range(64):  # more than the buffer plus what TCP's windows hold
                    edge.send("s", b"x" * (1 << 19), timeout=0.5)
        finally:
            edge.close()
            result["link"].close()


def test_options_refuse_a_heartbeat_slower_than_the_dead_timeout():
    with pytest.raises(ValueError, match="heartbeat_s"):
        LinkOptions(heartbeat_s=5.0, dead_after_s=2.0)
