"""A training run's robot at the edge through a real link cut: it keeps acting on its last weights
while the link is down (episodes go to the spool), holds once the link has been down for
``edge.max_offline_s`` (no step while held, and no safety stop however long the hold), and when the
link returns acts again, loads the next version and drains the spool; the outage's length and the
episodes spooled during it are counted.

Real parts: the simulated Sawyer behind the safety layer in the run's control loop, the edge node's
transport, the edge client and its disk spool, the cloud hub, and the link emulator's silent cut."""

import importlib.util
import threading
import time

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None, reason="needs metaworld")

from infinirl.config import to_dataclass  # noqa: E402
from infinirl.edge.cloud_hub import CloudHub, HubOptions, wait_for  # noqa: E402
from infinirl.edge.edge_client import EdgeClient, EdgeOptions  # noqa: E402
from infinirl.edge.emulator import EmulatorSpec, LinkEmulator  # noqa: E402
from infinirl.edge.link import LinkOptions  # noqa: E402
from infinirl.edge.robot_node import EdgeRobotNode  # noqa: E402
from infinirl.edge.spool import EpisodeSpool  # noqa: E402
from infinirl.realworld.control_loop import RobotControlLoop, unit_box  # noqa: E402
from infinirl.runners.realworld_sac import env_spec_of, net_spec_of, robot_setup_of  # noqa: E402
from infinirl.runners.realworld_sac_config import RealWorldSACConfig  # noqa: E402

LINK = LinkOptions(connect_timeout_s=2.0, heartbeat_s=0.2, dead_after_s=1.0)
EDGE = EdgeOptions(reconnect_min_s=0.1, reconnect_max_s=0.3, link=LINK)


def a_cfg(tmp_path):
    return to_dataclass(RealWorldSACConfig, {
        "output_dir": str(tmp_path / "run"),
        "robot": {"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 50.0, "image_size": None}},
        "task": {"max_episode_steps": 10}, "network": {"actor_hidden": [16], "critic_hidden": [16]},
        "pipeline": {"transport": "edge"},
        "edge": {"certs": str(tmp_path), "heartbeat_s": 0.2, "dead_after_s": 1.0, "max_offline_s": 600.0}})


def actor_weights(cfg, loop, shift):
    actor = net_spec_of(cfg).build_actor(loop.obs_dim, unit_box(loop.action_dim))
    return {name: tensor.detach().numpy() + shift for name, tensor in actor.state_dict().items()}


def test_the_edge_robot_acts_offline_then_holds_and_resumes_when_the_link_returns(credentials, tmp_path):
    cfg = a_cfg(tmp_path)
    received, lock = [], threading.Lock()

    def on_episode(edge, episode_id, episode):
        with lock:
            received.append(episode_id)

    loop = RobotControlLoop(robot_setup_of(cfg), env_spec_of(cfg), net_spec_of(cfg), seed=0)
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=on_episode,
                  options=HubOptions(link=LINK)) as hub, \
            LinkEmulator(EmulatorSpec.from_rtt(rtt_ms=10, mbit_per_s=None), hub.address) as emulator:
        client = EdgeClient(emulator.address, credentials["edge-0"], name="edge-0",
                            spool=EpisodeSpool(tmp_path / "spool"), options=EDGE).start()
        node = EdgeRobotNode(cfg, loop, client)
        try:
            assert client.wait_connected(20.0)
            hub.publish(actor_weights(cfg, loop, 0.0), 1)
            node.start()
            assert wait_for(lambda: loop.policy_version == 1 and len(received) >= 2, 60.0)

            emulator.cut()  # silent: the edge notices after dead_after_s
            assert wait_for(lambda: not client.connected, 10.0)
            submitted = client.counts["episodes_submitted"]
            assert wait_for(lambda: client.counts["episodes_submitted"] > submitted, 30.0)  # acting offline
            assert node.counts["offline_holds"] == 0 and loop.policy_version == 1
            cfg.edge.max_offline_s = 0.5  # the bound passes (read before every step)
            assert wait_for(lambda: node.counts["offline_holds"] == 1, 20.0)
            held_at = loop.counts["steps"]
            time.sleep(cfg.robot.heartbeat_deadline_s + 0.5)  # longer than the safety heartbeat deadline
            assert loop.counts["steps"] == held_at  # held: not one step
            assert loop.policy_version == 1 and not client.connected
            assert node.stats()[0]["safety_events"].get("heartbeat_stop", 0) == 0  # a hold, not a stop

            emulator.restore()
            assert wait_for(lambda: client.connected, 20.0)
            hub.publish(actor_weights(cfg, loop, 0.01), 2)
            assert wait_for(lambda: loop.policy_version == 2 and loop.counts["steps"] > held_at, 60.0)
            assert client.wait_drained(60.0)
            stats = node.stop()[0]
        finally:
            node.stop()
            loop.close()
            client.close()
    outage = client.last_outage
    assert outage["offline_s"] > cfg.robot.heartbeat_deadline_s and outage["episodes_spooled"] >= 1
    assert client.counts["outages"] == 1 and client.counts["episodes_spooled_offline"] == outage["episodes_spooled"]
    counts = stats["counts"]
    assert counts["offline_holds"] == 1 and counts["offline_hold_s"] > cfg.robot.heartbeat_deadline_s
    assert counts["link_outages"] == 1
    assert len(received) == len(set(received)) == client.counts["episodes_submitted"]  # each once
