"""The intervention page at the edge, used from the cloud through the link: a web intervention device
beside the (simulated) robot, the edge client dialling the cloud hub through the link emulator (60 ms
RTT, 20 Mbit/s), and HTTP requests to the cloud's page port: the page loads, take-over, an action, a
success mark and a camera frame travel through the one authenticated connection and reach the
control loop's poll(), while episodes still go up on the same link. The edge opens no port for it."""

import http.client
import importlib.util
import io
import json
import socket
import subprocess
import sys
import time
from importlib import resources

import numpy as np
import pytest

from infinirl.edge.cloud_hub import CloudHub, HubOptions, wait_for
from infinirl.edge.credentials import issue_credentials
from infinirl.edge.edge_client import EdgeClient, EdgeOptions
from infinirl.edge.emulator import EmulatorSpec, LinkEmulator
from infinirl.edge.link import LinkOptions
from infinirl.edge.tunnel import TunnelListener
from infinirl.realworld.intervention.web import WebInterventionDevice

pytest.importorskip("aiohttp")  # the page's server

LINK = LinkOptions(connect_timeout_s=5.0, heartbeat_s=0.3, dead_after_s=3.0)
TOKEN = "through-the-link"
TIMEOUT = 20.0


class Page:
    """An HTTP/1.1 client on the cloud's page port; one kept-alive connection, like a browser tab's."""

    def __init__(self, address):
        self.connection = http.client.HTTPConnection(*address, timeout=TIMEOUT)

    def request(self, method, path, body=None):
        self.connection.request(method, f"{path}?token={TOKEN}", body=None if body is None else json.dumps(body),
                                headers={"Content-Type": "application/json"})
        response = self.connection.getresponse()
        return response.status, response.getheader("Content-Type"), response.read()

    def json(self, method, path, body=None):
        status, _, data = self.request(method, path, body)
        assert status == 200, data
        return json.loads(data)


@pytest.fixture(scope="module")
def credentials(tmp_path_factory):
    return issue_credentials(tmp_path_factory.mktemp("pki"), edges=("edge-0",))


@pytest.fixture()
def page_through_link(credentials):
    episodes = []
    device = WebInterventionDevice(action_dim=4, token=TOKEN, heartbeat_timeout_s=None)
    hub = CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=lambda *args: episodes.append(args),
                   options=HubOptions(link=LINK)).start()
    emulator = LinkEmulator(EmulatorSpec.from_rtt(rtt_ms=60, mbit_per_s=20), hub.address)
    client = EdgeClient(emulator.address, credentials["edge-0"], name="edge-0",
                        options=EdgeOptions(link=LINK), tunnel_targets={"page": (device.host, device.port)}).start()
    listener = TunnelListener(("127.0.0.1", 0), lambda: hub.tunnel("edge-0"), service="page").start()
    try:
        assert client.wait_connected(TIMEOUT)
        assert wait_for(lambda: hub.tunnel() is not None, TIMEOUT)
        yield device, listener, client, hub, episodes
    finally:
        listener.close()
        client.close()
        emulator.close()
        hub.close()
        device.close()


def test_the_page_at_the_edge_is_used_from_the_cloud(page_through_link):
    device, listener, client, hub, episodes = page_through_link
    frame = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    device.show({"corner": frame}, {"episode": 3})
    page = Page(listener.address)

    status, content_type, html = page.request("GET", "/")
    assert status == 200 and content_type.startswith("text/html") and b"<html" in html.lower()
    assert html == resources.files("infinirl.realworld.intervention").joinpath("static", "index.html").read_bytes()
    state = page.json("GET", "/api/state")
    assert state["actor"] == "policy" and state["info"] == {"episode": 3} and state["cameras"] == ["corner"]

    taken = page.json("POST", "/api/takeover")
    assert taken["actor"] == "human"
    session = taken["session"]
    assert page.json("POST", "/api/action", {"session": session, "action": [0.5, -0.25, 1.0, -1.0]}) == {"ok": True}
    assert page.json("POST", "/api/mark", {"mark": "success"})["marks_pending"] == ["success"]
    human = device.poll(policy_action=np.zeros(4))
    assert human.active and human.marks == ("success",)
    np.testing.assert_array_equal(human.action, [0.5, -0.25, 1.0, -1.0])

    status, content_type, jpeg = page.request("GET", "/api/frame/corner")
    assert status == 200 and content_type == "image/jpeg"
    from PIL import Image

    assert Image.open(io.BytesIO(jpeg)).size == (64, 48)

    assert page.json("POST", "/api/handback", {"session": session})["actor"] == "policy"
    assert not device.poll().active
    status, _, _ = page.request("POST", "/api/action", {"session": session, "action": [2.0, 0, 0, 0]})
    assert status == 400  # the device's own checks answer through the tunnel too

    # episodes share the link with the page meanwhile
    episode = {"state": np.zeros((3, 9), np.float32), "action": np.zeros((2, 4), np.float32),
               "reward": np.zeros(2, np.float32)}
    client.submit(episode)
    assert client.wait_drained(TIMEOUT) and len(episodes) == 1
    assert page.json("GET", "/api/state")["polls"] == 2
    page.connection.close()
    end = hub.tunnel("edge-0")
    assert wait_for(lambda: end.connections() == 0, TIMEOUT)
    assert not end.failures and not client.tunnel.failures
    assert device.stats.takeovers == 1 and device.stats.marks == 1


def test_the_page_port_closes_connections_while_no_edge_is_connected(page_through_link):
    device, listener, client, hub, episodes = page_through_link
    client.close()
    assert wait_for(lambda: hub.tunnel() is None, TIMEOUT)
    page = Page(listener.address)
    with pytest.raises((ConnectionError, http.client.RemoteDisconnected)):
        page.request("GET", "/api/state")
    assert listener.counts["no_edge"] == 1


@pytest.mark.skipif(importlib.util.find_spec("metaworld") is None,
                    reason="needs metaworld (the edge node's simulated Sawyer)")
def test_the_edge_and_cloud_commands_serve_the_page(tmp_path):
    """``cloud --page-port`` and ``edge --page-target``: the page beside a running edge node is
    reached on the cloud node's port."""
    issue_credentials(tmp_path / "pki", edges=("edge-0",))
    device = WebInterventionDevice(action_dim=4, token=TOKEN, heartbeat_timeout_s=None)
    cloud = _spawn("cloud", "--listen", "127.0.0.1:0", "--certs", str(tmp_path / "pki"),
                   "--replay", str(tmp_path / "replay"), "--page-port", "0")
    edge = None
    try:
        started = _json_line(cloud)
        edge = _spawn("edge", "--cloud", f"127.0.0.1:{started['listening'][1]}", "--certs", str(tmp_path / "pki"),
                      "--name", "edge-0", "--robot", "sim_sawyer",
                      "--robot-options", json.dumps({"image_size": 32, "control_hz": 20}),
                      "--max-episode-steps", "10", "--hidden", "16,16", "--seconds", "120",
                      "--page-target", f"{device.host}:{device.port}")
        page_address = ("127.0.0.1", started["page"][1])

        def taken_over():
            try:
                return Page(page_address).json("POST", "/api/takeover")["actor"] == "human"
            except (ConnectionError, http.client.HTTPException):
                return False  # the edge's link is not up yet

        assert wait_for(taken_over, 120.0)  # the edge node imports its robot before it dials
        assert device.poll().active
        assert _json_line(edge)["episode"] == 1  # its robot runs meanwhile
    finally:
        for process in (edge, cloud):
            if process is not None:
                _stop(process)
        device.close()


def test_a_busy_page_port_stops_the_cloud_command_with_one_line(tmp_path):
    issue_credentials(tmp_path / "pki", edges=("edge-0",))
    with socket.create_server(("127.0.0.1", 0)) as busy:
        cloud = _spawn("cloud", "--listen", "127.0.0.1:0", "--certs", str(tmp_path / "pki"),
                       "--replay", str(tmp_path / "replay"), "--page-port", str(busy.getsockname()[1]))
        out, err = cloud.communicate(timeout=120.0)
    assert cloud.returncode == 2 and out == ""
    assert err.startswith("error: --page-port") and err.count("\n") == 1


def _spawn(*args):
    return subprocess.Popen([sys.executable, "-m", "infinirl.edge", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)


def _json_line(process, timeout=120.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            raise AssertionError(f"process ended: {process.stderr.read()[-3000:]}")
        if line.startswith("{"):
            return json.loads(line)
    raise AssertionError("no JSON line in time")


def _stop(process):
    if process.poll() is None:
        process.terminate()
    try:
        process.communicate(timeout=30.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
