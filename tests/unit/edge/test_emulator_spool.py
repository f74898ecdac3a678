"""The link emulator's token bucket (on a fake clock), its latency and cut/restore; the edge's
episode spool (bounded, atomic files, survives a restart, sets torn files aside, refuses what no
frame can carry, durable in the edge commands)."""

import os
import socket
import threading
import time

import numpy as np
import pytest

from infinirl.edge.codec import encode_episode
from infinirl.edge.emulator import EmulatorSpec, LinkEmulator, TokenBucket
from infinirl.edge.spool import CORRUPT_FOLDER, EpisodeSpool, EpisodeTooLargeError, SpoolFullError


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


def payload(episode_id, size=300):
    """An encoded episode of exactly ``size`` bytes (the length of a field's name makes it up)."""
    one = len(encode_episode({"x": np.zeros(0, np.uint8)}, episode_id=episode_id))
    encoded = encode_episode({"x" * (size - one + 1): np.zeros(0, np.uint8)}, episode_id=episode_id)
    assert len(encoded) == size
    return encoded


def test_spool_keeps_order_bounds_and_survives_a_restart(tmp_path):
    spool = EpisodeSpool(tmp_path, max_bytes=750)
    spool.put("e-0", payload("e-0"))
    spool.put("e-1", payload("e-1"))
    with pytest.raises(SpoolFullError, match="full: 2 episodes, 600 bytes"):
        spool.put("e-2", payload("e-2"))
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    reopened = EpisodeSpool(tmp_path, max_bytes=750)
    assert reopened.ids() == ["e-0", "e-1"] and reopened.read("e-1") == payload("e-1") and reopened.bytes == 600
    assert reopened.remove("e-0") and not reopened.remove("e-0")
    reopened.put("e-2", payload("e-2"))
    assert EpisodeSpool(tmp_path).ids() == ["e-1", "e-2"] and reopened.set_aside == []
    memory = EpisodeSpool(max_episodes=1)
    memory.put("m", b"x")
    with pytest.raises(SpoolFullError, match="memory"):
        memory.put("n", b"y")


def test_opening_a_spool_moves_torn_and_foreign_files_aside(tmp_path):
    spool = EpisodeSpool(tmp_path)
    for index in range(3):
        spool.put(f"e-{index}", payload(f"e-{index}"))
    first, second, third = sorted(tmp_path.glob("*.episode"))
    first.write_bytes(first.read_bytes()[:250])  # torn: a crash of a spool that did not fsync
    third.write_bytes(payload("e-other"))  # another episode than its name says
    (tmp_path / "notes.episode").write_bytes(b"x")
    (tmp_path / f".{second.name}.abc123.tmp").write_bytes(b"half")  # a write a crash cut off
    reopened = EpisodeSpool(tmp_path)
    assert reopened.ids() == ["e-1"] and reopened.bytes == 300
    assert sorted(reopened.set_aside) == sorted([first.name, third.name, "notes.episode"])
    assert sorted(p.name for p in (tmp_path / CORRUPT_FOLDER).iterdir()) == sorted(reopened.set_aside)
    assert not list(tmp_path.glob(".*.tmp"))
    assert EpisodeSpool(tmp_path).ids() == ["e-1"]  # what was set aside stays aside


def test_a_spool_file_gone_while_read_is_none_and_forgotten(tmp_path):
    spool = EpisodeSpool(tmp_path)
    spool.put("e-0", payload("e-0"))
    next(tmp_path.glob("*.episode")).unlink()  # what an acknowledgement racing the read does, or an operator
    assert spool.read("e-0") is None and spool.ids() == [] and spool.bytes == 0
    assert not spool.remove("e-0")


def test_an_episode_larger_than_a_frame_is_refused_and_not_kept(tmp_path, monkeypatch):
    monkeypatch.setattr("infinirl.edge.spool.MAX_PAYLOAD_BYTES", 250)
    for spool in (EpisodeSpool(tmp_path), EpisodeSpool()):
        with pytest.raises(EpisodeTooLargeError, match="more than a frame of the link carries"):
            spool.put("e-0", payload("e-0"))
        assert isinstance(EpisodeTooLargeError(), SpoolFullError)  # counted like a full spool by its callers
        assert spool.ids() == [] and spool.bytes == 0
    assert not list(tmp_path.glob("*.episode"))


class _Refused(Exception):
    pass


def test_the_edge_nodes_keep_their_spool_durable(tmp_path, credentials, monkeypatch):
    """An episode the robot recorded must survive a power loss at the edge: both edge commands open
    their on-disk spool with ``durable=True``."""
    from infinirl.config import to_dataclass
    from infinirl.edge import __main__ as cli
    from infinirl.edge import robot_node
    from infinirl.runners.realworld_sac_config import RealWorldSACConfig

    opened = []

    def recording(*args, **kwargs):
        opened.append(kwargs)
        raise _Refused

    certs = os.path.dirname(credentials["edge-0"].cert)
    monkeypatch.setattr(robot_node, "EpisodeSpool", recording)
    cfg = to_dataclass(RealWorldSACConfig, {"output_dir": str(tmp_path / "run"), "pipeline": {"transport": "edge"},
                                            "edge": {"certs": certs}})
    with pytest.raises(_Refused):
        robot_node.run_robot_node(cfg, lambda: None, cloud=("127.0.0.1", 1), certs=certs, name="edge-0")
    monkeypatch.setattr("infinirl.edge.spool.EpisodeSpool", recording)
    monkeypatch.setattr(cli, "_stop_event", threading.Event)  # no signal handlers in the test process
    with pytest.raises(_Refused):
        cli.main(["edge", "--cloud", "127.0.0.1:1", "--certs", certs, "--spool", str(tmp_path / "spool")])
    assert [kwargs.get("durable") for kwargs in opened] == [True, True]
