"""The env link's socket transport cleans up after itself: every env rank of every run opens a
Unix socket in a fresh temporary directory, so a directory left behind per link adds up (a test
suite left hundreds in /tmp before this was fixed)."""

from __future__ import annotations

import os
import threading

from infinirl.components.env_link import accept, close_server, connect, open_server


def connected_pair(server, address):
    """(env side, rollout side) of one socket link."""
    client = {}
    connecting = threading.Thread(target=lambda: client.setdefault("link", connect(address)))
    connecting.start()
    env_side = accept(server)
    connecting.join(timeout=10)
    return env_side, client["link"]


def test_a_unix_socket_link_removes_its_directory_once_connected():
    server, address = open_server("socket")
    directory = os.path.dirname(address["address"])
    assert os.path.isdir(directory)
    env_side, rollout_side = connected_pair(server, address)
    try:
        rollout_side.send({"obs": 1})
        assert env_side.recv() == {"obs": 1}
        assert not os.path.exists(directory)
    finally:
        env_side.close()
        rollout_side.close()


def test_a_server_nobody_connected_to_removes_its_directory_when_closed():
    server, address = open_server("socket")
    directory = os.path.dirname(address["address"])
    close_server(server)
    assert not os.path.exists(directory)
    close_server(server)  # closing twice is harmless


def test_a_socket_link_counts_the_pickled_bytes_it_sends():
    """What the scheduler charges a link between nodes: each end counts exactly the bytes it sent."""
    import pickle

    import numpy as np

    env_side, rollout_side = connected_pair(*open_server("socket"))
    client = {"link": rollout_side}
    try:
        observation = {"pixels": np.zeros((4, 3, 64, 64), np.uint8), "state": np.arange(39, dtype=np.float32)}
        env_side.send(observation)
        env_side.send(observation)
        got = client["link"].recv()
        assert np.array_equal(got["pixels"], observation["pixels"]) and got["state"].dtype == np.float32
        client["link"].recv()
        assert env_side.bytes_sent == 2 * len(pickle.dumps(observation, protocol=pickle.DEFAULT_PROTOCOL))
        assert client["link"].bytes_sent == 0
        client["link"].send((0, np.ones(4, np.float32)))
        assert env_side.recv()[0] == 0 and client["link"].bytes_sent > 16
    finally:
        env_side.close()
        client["link"].close()
