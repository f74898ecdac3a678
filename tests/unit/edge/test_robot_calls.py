"""The trainer's calls on the robot at the edge, over a real mutual-TLS link: answers and episodes
come back exact, a failure at the edge comes back as one line, an unknown method names the known
ones, a call whose link drops is repeated on the next link, and a caller with no edge gives up at
its timeout with the reason."""

import numpy as np
import pytest

from infinirl.edge.cloud_hub import CloudHub, HubOptions, wait_for
from infinirl.edge.codec import encode_episode
from infinirl.edge.edge_client import EdgeClient, EdgeOptions
from infinirl.edge.link import LinkOptions
from infinirl.edge.robot_calls import ROBOT_CALLS, ROBOT_REPLIES, RobotCaller, RobotCallError, RobotCallServer

LINK = LinkOptions(connect_timeout_s=2.0, heartbeat_s=0.2, dead_after_s=1.0)


def an_episode(steps=5):
    rng = np.random.default_rng(steps)
    return {"state": rng.normal(size=(steps + 1, 3)).astype(np.float32),
            "action": rng.uniform(-1, 1, (steps, 2)).astype(np.float32),
            "version": np.full(steps, -1, np.int64)}


@pytest.fixture()
def linked(credentials):
    hub = CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=lambda *a: None,
                   options=HubOptions(link=LINK)).start()
    client = EdgeClient(hub.address, credentials["edge-0"], name="edge-0",
                        options=EdgeOptions(reconnect_min_s=0.05, reconnect_max_s=0.2, link=LINK)).start()
    assert client.wait_connected(10.0)
    assert wait_for(lambda: hub.link("edge-0") is not None, 10.0)
    try:
        yield hub, client
    finally:
        client.close()
        hub.close()


def test_answers_episodes_and_errors_travel_back(linked):
    hub, client = linked
    episode = an_episode()

    def fail():
        raise ValueError("the gripper is not calibrated")

    handlers = {"describe": lambda: ({"obs_dim": 3, "cameras": {"corner": [8, 8]}}, []),
                "demonstrations": lambda n: (None, [episode] * n), "fail": fail}
    server = RobotCallServer(client, handlers).start()
    try:
        caller = RobotCaller(hub, "edge-0")
        assert caller.call("describe", timeout=10.0) == ({"obs_dim": 3, "cameras": {"corner": [8, 8]}}, [])
        result, episodes = caller.call("demonstrations", 2, timeout=10.0)
        assert result is None and len(episodes) == 2
        for got in episodes:
            assert set(got) == set(episode) and all(np.array_equal(got[k], episode[k]) for k in episode)
        with pytest.raises(RobotCallError, match="'fail' failed: ValueError: the gripper is not calibrated") as error:
            caller.call("fail", timeout=10.0)
        assert "\n" not in str(error.value)
        with pytest.raises(RobotCallError, match="unknown method 'reboot'; known: demonstrations, describe, fail"):
            caller.call("reboot", timeout=10.0)
    finally:
        server.close()


def test_a_call_whose_link_drops_is_repeated_on_the_next_link(linked):
    hub, client = linked
    calls = []

    def stats():
        calls.append(1)
        if len(calls) == 1:  # the link drops before the answer leaves
            client.link.close("cut by the test")
        return {"episodes": len(calls)}, []

    server = RobotCallServer(client, {"stats": stats}).start()
    try:
        assert RobotCaller(hub, "edge-0").call("stats", timeout=30.0) == ({"episodes": 2}, [])
        assert len(calls) == 2
    finally:
        server.close()


def test_episode_frames_left_by_a_call_that_timed_out_do_not_break_the_next_call(linked):
    """A call that gave up partway through its answer's episodes leaves the rest in the reply stream;
    the next call skips them, and a reply it cannot read is a :class:`RobotCallError`, not a
    ``JSONDecodeError``."""
    hub, client = linked
    episode = an_episode()
    server = RobotCallServer(client, {"demonstrations": lambda n: (None, [episode] * n),
                                      "stats": lambda: ({"episodes": 3}, [])}).start()
    try:
        caller = RobotCaller(hub, "edge-0")
        for index in (1, 2):  # what an earlier call's answer still had on the way when it timed out
            client.link.send(ROBOT_REPLIES, encode_episode(episode, episode_id=f"reply-0-{index}"), timeout=5.0)
        assert caller.call("stats", timeout=10.0) == ({"episodes": 3}, [])
        result, episodes = caller.call("demonstrations", 2, timeout=10.0)
        assert result is None and len(episodes) == 2 and np.array_equal(episodes[1]["action"], episode["action"])
        client.link.send(ROBOT_REPLIES, b"not json", timeout=5.0)
        with pytest.raises(RobotCallError, match="'stats': unreadable reply"):
            caller.call("stats", timeout=10.0)
        assert caller.call("stats", timeout=10.0) == ({"episodes": 3}, [])  # its answer was read and skipped
    finally:
        server.close()


def test_a_malformed_call_is_ignored_and_the_edge_answers_the_next(linked):
    hub, client = linked
    server = RobotCallServer(client, {"stats": lambda: ({"episodes": 1}, [])}).start()
    try:
        hub.link("edge-0").send(ROBOT_CALLS, b"[1, 2]", timeout=5.0)
        hub.link("edge-0").send(ROBOT_CALLS, b"not json", timeout=5.0)
        assert RobotCaller(hub, "edge-0").call("stats", timeout=10.0) == ({"episodes": 1}, [])
    finally:
        server.close()


def test_a_caller_with_no_edge_gives_up_with_the_reason(credentials):
    with CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=lambda *a: None,
                  options=HubOptions(link=LINK)) as hub:
        with pytest.raises(RobotCallError, match="edge edge-0 not connected within 0 s"):
            RobotCaller(hub, "edge-0").call("stats", timeout=0.3)

        def gone():
            raise RuntimeError("the edge node exited with status 1: error: no robot")

        with pytest.raises(RuntimeError, match="no robot"):
            RobotCaller(hub, "edge-0", check=gone).call("stats", timeout=30.0)
