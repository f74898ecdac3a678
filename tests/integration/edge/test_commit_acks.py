"""The edge forgets an episode only once the learner committed it to its replay store: the trainer
side dies with episodes on the learner's channel (delivered, not committed) and with episodes
committed whose acknowledgement never went out; after a trainer restarts on the same address and
the edge reconnects, every episode is in the store exactly once and the edge's spool is empty.

Real parts: the edge client and its disk spool, the trainer's link and hub over mutual TLS, a Ray
channel, the learner worker (in this process) and its replay store on disk."""

import socket

import numpy as np
import pytest

from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
from infinirl.config import to_dataclass
from infinirl.edge.cloud_hub import wait_for
from infinirl.edge.codec import FrameOptions
from infinirl.edge.credentials import TlsFiles, issue_credentials
from infinirl.edge.edge_client import EdgeClient, EdgeOptions
from infinirl.edge.link import LinkOptions
from infinirl.edge.spool import EpisodeSpool
from infinirl.edge.trainer_link import TrainerLink
from infinirl.realworld.learner_worker import SOURCE_ID, LearnerLoopSpec, RealWorldLearnerWorker
from infinirl.realworld.replay import ReplayStore
from infinirl.runners.realworld_sac_config import RealWorldSACConfig
from infinirl.runtime import Channel

OBS, ACT, STEPS = 3, 2, 4
EDGE = EdgeOptions(reconnect_min_s=0.1, reconnect_max_s=0.3, window=8,
                   link=LinkOptions(connect_timeout_s=2.0, heartbeat_s=0.2, dead_after_s=1.0))


def an_episode(index):
    return {"state": np.full((STEPS + 1, OBS), index, np.float32), "action": np.zeros((STEPS, ACT), np.float32),
            "reward": np.full(STEPS, index, np.float32), "terminated": np.zeros(STEPS, np.float32),
            "version": np.full(STEPS, -1, np.int64)}


def a_learner(replay):
    loop = LearnerLoopSpec(replay_dir=str(replay), learning_starts=10**6, durable=False)
    return RealWorldLearnerWorker(SACNetSpec(actor_hidden=(8,), critic_hidden=(8,)), SACUpdateSpec(batch_size=4),
                                  loop, OBS, ACT)


@pytest.fixture()
def trainer_cfg(tmp_path):
    issue_credentials(tmp_path / "pki", edges=("edge-0",))
    with socket.create_server(("127.0.0.1", 0)) as probe:  # one address for the trainer and its restart
        port = probe.getsockname()[1]
    return to_dataclass(RealWorldSACConfig, {
        "output_dir": str(tmp_path / "run"), "pipeline": {"transport": "edge"},
        "edge": {"listen": f"127.0.0.1:{port}", "certs": str(tmp_path / "pki"), "heartbeat_s": 0.2,
                 "dead_after_s": 1.0}})


def test_episodes_survive_a_trainer_that_dies_before_committing_them(ray_cluster, trainer_cfg, tmp_path):
    replay = tmp_path / "replay"
    host, _, port = trainer_cfg.edge.listen.rpartition(":")
    client = EdgeClient((host, int(port)), TlsFiles.in_folder(trainer_cfg.edge.certs, "edge-0"), name="edge-0",
                        spool=EpisodeSpool(tmp_path / "spool"), frames=FrameOptions(format="png"), options=EDGE)
    first_channel = Channel.create("commit-acks-first")
    first = TrainerLink(trainer_cfg, first_channel).start()
    client.start()
    try:
        ids = [client.submit(an_episode(i)) for i in range(6)]
        assert wait_for(lambda: first.hub.counts["episodes"] == 6, 30.0)  # all on the channel: none acknowledged
        assert len(client.spool) == 6
        # The learner takes two and commits them, but the trainer dies before it reports them ...
        learner = a_learner(replay)
        taken = first_channel.get_batch(2, key="episodes", timeout=10.0)
        assert [e[SOURCE_ID] for e in taken] == ids[:2]
        learner.add_and_update(taken, 0)
        learner.close()
        # ... and the other four die with it on the channel.
        first.close()
        first_channel.destroy()
        assert wait_for(lambda: not client.connected, 10.0) and len(client.spool) == 6

        second_channel = Channel.create("commit-acks-second")
        second = TrainerLink(trainer_cfg, second_channel).start()
        learner = a_learner(replay)
        learner.start(second_channel)
        try:
            assert client.wait_drained(60.0)  # every episode acknowledged, so every one committed
            status = learner.stop()
        finally:
            learner.close()
            second.close()
            second_channel.destroy()
    finally:
        client.close()
    assert status["counts"]["duplicate_episodes"] == 2 and status["counts"]["episodes"] == 4
    with ReplayStore(str(replay), writable=False) as store:
        assert store.num_episodes == 6 and sorted(store.sources.sources()) == sorted(ids)  # each once
        for index, episode_id in enumerate(ids):
            stored = store.episode(store.episode_of_source(episode_id))
            assert np.array_equal(stored["state"], an_episode(index)["state"])
    assert not list((tmp_path / "spool").glob("*.episode"))
