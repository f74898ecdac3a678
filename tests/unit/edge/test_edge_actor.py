"""The edge's policy: random warm-up or hold before weights arrive, the held weights while the link
is down for at most the staleness bound, a hold beyond it (arm target kept, gripper as commanded)."""

import importlib.util

import numpy as np
import pytest
import torch

from infinirl.edge.codec import HeldWeights
from infinirl.edge.edge_actor import HOLD_VERSION, EdgeActor, hold_action, load_weights
from infinirl.edge.edge_client import EdgeClient, EdgeOptions
from infinirl.edge.link import LinkOptions
from infinirl.models.sac_nets import SquashedGaussianActor
from infinirl.realworld.driver import make_robot
from infinirl.realworld.episodes import RANDOM_VERSION
from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec


@pytest.fixture(scope="module")
def env():
    if importlib.util.find_spec("metaworld") is None:
        pytest.skip("needs metaworld (the simulated Sawyer)")
    robot = make_robot("sim_sawyer", control_hz=50.0, image_size=None)
    robot.connect()
    try:
        yield RobotEnv(robot, RobotEnvSpec(observations=("proprio",), max_episode_steps=5))
    finally:
        robot.close()


def test_hold_keeps_the_arm_target_and_the_gripper_command(env):
    env.reset()
    env.step(np.array([0.5, -0.5, 0.2, -0.7], np.float32))
    assert np.array_equal(hold_action(env), np.array([0.0, 0.0, 0.0, -0.7], np.float32))


def test_the_actor_acts_within_the_staleness_bound_and_holds_beyond_it(env, credentials):
    import socket

    closed = socket.create_server(("127.0.0.1", 0))
    address = closed.getsockname()
    closed.close()  # nothing listens: the client stays offline
    client = EdgeClient(address, credentials["edge-0"], name="edge-0", options=EdgeOptions(
        reconnect_min_s=0.05, reconnect_max_s=0.1, link=LinkOptions(connect_timeout_s=0.2, heartbeat_s=0.1,
                                                                     dead_after_s=1.0))).start()
    net = SquashedGaussianActor(env.observation_size(), env.action_dim, [-1.0] * 4, [1.0] * 4, hidden=(8,))
    try:
        obs = env.reset()
        random_warmup = EdgeActor(net, client, max_offline_s=60.0, warmup="random")
        assert random_warmup.act(env, obs)[1] == RANDOM_VERSION
        holding = EdgeActor(net, client, max_offline_s=60.0, warmup="hold")
        action, version = holding.act(env, obs)
        assert version == HOLD_VERSION and np.array_equal(action, hold_action(env))
        client.weights = HeldWeights.of(7, {n: t.numpy() + 0.5 for n, t in net.state_dict().items()})
        action, version = holding.act(env, obs, deterministic=True)
        assert version == 7 and np.all(np.abs(action) <= 1.0)
        assert torch.allclose(holding.actor.mean.bias, torch.from_numpy(client.weights.tensors["mean.bias"]))
        strict = EdgeActor(net, client, max_offline_s=0.0)
        assert strict.act(env, obs)[1] == HOLD_VERSION and strict.holds == 1
    finally:
        client.close()


def test_weights_with_no_place_in_the_actor_are_refused():
    net = SquashedGaussianActor(3, 2, [-1.0] * 2, [1.0] * 2, hidden=(4,))
    with pytest.raises(KeyError, match="no place"):
        load_weights(net, {"encoder.weight": np.zeros((2, 2), np.float32)})
