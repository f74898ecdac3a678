"""The link emulator's token bucket (on a fake clock), its latency and cut/restore; the edge's
episode spool (bounded, atomic files, survives a restart)."""

import socket
import threading
import time

import pytest

from infinirl.edge.emulator import EmulatorSpec, LinkEmulator, TokenBucket
from infinirl.edge.spool import EpisodeSpool, SpoolFullError


def test_token_bucket_paces_to_its_rate_after_the_burst():
    now = [0.0]
    bucket = TokenBucket(1000.0, depth=500, clock=lambda: now[0])
    assert bucket.delay_for(500) == 0.0  # the saved-up burst
    assert bucket.delay_for(250) == pytest.approx(0.25)
    now[0] = 0.25
    assert bucket.delay_for(100) == pytest.approx(0.1)
    now[0] = 10.0  # idle: refills to the depth only
    assert bucket.delay_for(600) == pytest.approx(0.1)
    assert TokenBucket(None, depth=1).delay_for(10**9) == 0.0


@pytest.fixture()
def echo_server():
    server = socket.create_server(("127.0.0.1", 0))

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return

            def echo(conn=conn):
                with conn:
                    while data := conn.recv(65536):
                        conn.sendall(data)

            threading.Thread(target=echo, daemon=True).start()

    threading.Thread(target=serve, daemon=True).start()
    yield server.getsockname()
    server.close()


def test_emulator_adds_latency_forwards_everything_and_cuts(echo_server):
    with LinkEmulator(EmulatorSpec.from_rtt(rtt_ms=60, mbit_per_s=20), echo_server) as emulator:
        client = socket.create_connection(emulator.address, timeout=5.0)
        started = time.monotonic()
        client.sendall(b"ping")
        assert client.recv(4) == b"ping"
        assert time.monotonic() - started >= 0.06  # a round trip is never shorter than the emulated RTT
        payload = bytes(range(256)) * 1000
        threading.Thread(target=client.sendall, args=(payload,), daemon=True).start()
        got = b""
        while len(got) < len(payload):
            got += client.recv(65536)
        assert got == payload
        emulator.cut()
        client.sendall(b"held")
        client.settimeout(0.3)
        with pytest.raises(TimeoutError):
            client.recv(4)
        emulator.restore()
        client.settimeout(5.0)
        assert client.recv(4) == b"held"  # a stall delays, it does not lose
        stats = emulator.stats()
        assert stats["bytes_up"] == stats["bytes_down"] == len(payload) + 8
        emulator.cut("reset")
        client.settimeout(5.0)
        assert client.recv(4) == b""  # the connection was closed
        with pytest.raises(OSError):
            refused = socket.create_connection(emulator.address, timeout=1.0)
            refused.settimeout(1.0)
            if refused.recv(1) == b"":
                raise ConnectionResetError("refused while cut")


def test_spool_keeps_order_bounds_and_survives_a_restart(tmp_path):
    spool = EpisodeSpool(tmp_path, max_bytes=250)
    spool.put("e-0", b"a" * 100)
    spool.put("e-1", b"b" * 100)
    with pytest.raises(SpoolFullError, match="full: 2 episodes, 200 bytes"):
        spool.put("e-2", b"c" * 100)
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    reopened = EpisodeSpool(tmp_path, max_bytes=250)
    assert reopened.ids() == ["e-0", "e-1"] and reopened.read("e-1") == b"b" * 100 and reopened.bytes == 200
    assert reopened.remove("e-0") and not reopened.remove("e-0")
    reopened.put("e-2", b"c" * 100)
    assert EpisodeSpool(tmp_path).ids() == ["e-1", "e-2"]
    memory = EpisodeSpool(max_episodes=1)
    memory.put("m", b"x")
    with pytest.raises(SpoolFullError, match="memory"):
        memory.put("n", b"y")
