"""An edge node and a cloud node in two network namespaces joined by a veth pair, with the link
emulator (60 ms RTT, 20 Mbit/s) in between: the edge dials out (it listens on no port), its episodes
reach the cloud's replay store once each although the link is cut mid-episode and restored, and an
edge with another CA's certificate is refused with nothing stored."""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import time

import pytest

from infinirl.edge.credentials import issue_credentials

pytestmark = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None,
                                reason="needs metaworld (the edge node's simulated Sawyer)")

CLOUD_IP, EDGE_IP = "10.213.0.2", "10.213.0.1"
CLOUD_PORT, EMULATOR_PORT = 7443, 7000


def _ip(*args, check=True):
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=30)


@pytest.fixture()
def namespaces():
    """Two namespaces, ``edge`` and ``cloud``, joined by a veth pair; removed afterwards."""
    if shutil.which("ip") is None:
        pytest.skip("the `ip` tool (iproute2) is not installed, so network namespaces cannot be made")
    tag = f"{os.getpid() % 100000}"
    edge, cloud = f"irl-edge-{tag}", f"irl-cloud-{tag}"
    made = []
    try:
        for name in (edge, cloud):
            result = _ip("netns", "add", name, check=False)
            if result.returncode != 0:
                pytest.skip(f"`ip netns add` is not available here ({result.stderr.strip()}); needs root and "
                            "network namespace support")
            made.append(name)
        _ip("link", "add", f"ve{tag}", "type", "veth", "peer", "name", f"vc{tag}")
        _ip("link", "set", f"ve{tag}", "netns", edge)
        _ip("link", "set", f"vc{tag}", "netns", cloud)
        for name, device, address in ((edge, f"ve{tag}", EDGE_IP), (cloud, f"vc{tag}", CLOUD_IP)):
            _ip("-n", name, "addr", "add", f"{address}/24", "dev", device)
            _ip("-n", name, "link", "set", device, "up")
            _ip("-n", name, "link", "set", "lo", "up")
        yield {"edge": edge, "cloud": cloud}
    finally:
        for name in made:
            _ip("netns", "del", name, check=False)  # takes its end of the veth pair with it


def _spawn(namespace, *args, stdin=False):
    return subprocess.Popen(["ip", "netns", "exec", namespace, sys.executable, "-m", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL, env={**os.environ})


def _json_line(process, timeout=120.0):
    """The next stdout line that is a JSON object (the nodes print their progress as JSON)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            raise AssertionError(f"process ended: {process.stderr.read()[-3000:]}")
        if line.startswith("{"):
            return json.loads(line)
    raise AssertionError("no JSON line in time")


def _stop(process, timeout=60.0):
    if process.poll() is None:
        process.terminate()
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    return out, err


@pytest.fixture()
def link_between(namespaces, tmp_path):
    """Credentials, the cloud node and the emulator (both in the cloud namespace)."""
    issue_credentials(tmp_path / "pki", edges=("edge-0",))
    issue_credentials(tmp_path / "pki-foreign", edges=("edge-0",))
    cloud = _spawn(namespaces["cloud"], "infinirl.edge", "cloud", "--listen", f"127.0.0.1:{CLOUD_PORT}",
                   "--certs", str(tmp_path / "pki"), "--replay", str(tmp_path / "replay"),
                   "--heartbeat-s", "0.3", "--dead-after-s", "2")
    emulator = _spawn(namespaces["cloud"], "infinirl.edge.emulator", "--listen", f"{CLOUD_IP}:{EMULATOR_PORT}",
                      "--target", f"127.0.0.1:{CLOUD_PORT}", "--rtt-ms", "60", "--mbit", "20", stdin=True)
    try:
        assert _json_line(cloud)["listening"] == ["127.0.0.1", CLOUD_PORT]
        assert _json_line(emulator)["listening"] == [CLOUD_IP, EMULATOR_PORT]
        yield cloud, emulator
    finally:
        _stop(emulator)
        _stop(cloud)


def _edge(namespaces, tmp_path, certs, episodes):
    return _spawn(namespaces["edge"], "infinirl.edge", "edge", "--cloud", f"{CLOUD_IP}:{EMULATOR_PORT}",
                  "--certs", str(certs), "--name", "edge-0", "--robot", "sim_sawyer",
                  "--robot-options", json.dumps({"image_size": 32, "control_hz": 20}), "--cameras", "corner",
                  "--max-episode-steps", "20", "--episodes", str(episodes), "--hidden", "32,32",
                  "--spool", str(tmp_path / "spool"), "--heartbeat-s", "0.3", "--dead-after-s", "2",
                  "--drain-s", "60")


def _command(emulator, line):
    emulator.stdin.write(line + "\n")
    emulator.stdin.flush()
    return _json_line(emulator)


def test_a_link_cut_mid_episode_loses_nothing(namespaces, link_between, tmp_path):
    cloud, emulator = link_between
    edge = _edge(namespaces, tmp_path, tmp_path / "pki", episodes=4)
    try:
        first = _json_line(edge)
        assert first["episode"] == 1 and first["steps"] == 20
        listening = subprocess.run(["ip", "netns", "exec", namespaces["edge"], "ss", "-Hltn"], capture_output=True,
                                   text=True, timeout=30).stdout
        assert listening.strip() == ""  # the edge dials out; it has no open port
        assert _command(emulator, "cut")["cut"]  # silent: the ends notice by their heartbeat timeout
        time.sleep(3.0)  # longer than dead_after_s, within the second episode
        assert not _command(emulator, "restore")["cut"]
        reports = [_json_line(edge) for _ in range(3)]
        assert [r["episode"] for r in reports] == [2, 3, 4]
        final = _json_line(edge)
        assert _command(emulator, "stats")["connections"] >= 2  # the edge reconnected after the cut
    finally:
        _stop(edge)
    assert final["drained"] and final["episodes_acked"] == 4 and final["disconnects"] >= 1
    assert final["connects"] >= 2 and final["spooled_episodes"] == 0
    cloud.terminate()
    out, err = _stop(cloud)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["replay_episodes"] == 4 and summary["episodes"] == 4, err[-2000:]
    assert summary["episodes_seen"] == 4 and summary["refusals"] == 0


def test_an_edge_with_another_cas_certificate_is_refused(namespaces, link_between, tmp_path):
    cloud, _ = link_between
    foreign = tmp_path / "pki-mixed"
    foreign.mkdir()
    shutil.copy(tmp_path / "pki" / "ca.pem", foreign / "ca.pem")  # trusts the right cloud
    for suffix in ("pem", "key"):
        shutil.copy(tmp_path / "pki-foreign" / f"edge-0.{suffix}", foreign / f"edge-0.{suffix}")
    edge = _edge(namespaces, tmp_path, foreign, episodes=1)
    out, err = _stop(edge, timeout=120.0) if edge.wait(timeout=120.0) is not None else ("", "")
    assert edge.returncode == 2
    assert "error: cloud at" in err and "refused this edge's certificate" in err
    cloud.terminate()
    out, err = _stop(cloud)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["refusals"] >= 1 and summary["replay_episodes"] == 0 and summary.get("episodes", 0) == 0
    assert "CERTIFICATE_VERIFY_FAILED" in err
