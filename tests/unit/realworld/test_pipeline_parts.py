"""Pure parts of the real-world pipeline: episode recording, staleness accounting, policy layouts of
heterogeneous robots, and the learner's staleness bound on a real replay store."""

import numpy as np
import pytest
import torch

from infinirl.realworld.control_loop import embodiment_action_mask
from infinirl.realworld.episodes import RANDOM_VERSION, EpisodeRecorder, episode_spec, staleness_of
from infinirl.realworld.robot_worker import PolicyLayout, policy_layouts


def test_recorder_gives_a_valid_store_episode():
    recorder = EpisodeRecorder({"state": np.zeros(3, np.float32), "pixels.front": np.zeros((2, 2, 3), np.uint8)})
    for t in range(4):
        recorder.add(np.full(2, t, np.float32), {"state": np.full(3, t + 1, np.float32),
                                                 "pixels.front": np.full((2, 2, 3), t, np.uint8)},
                     reward=float(t), terminated=t == 3, version=t - 1, success=t == 3)
    episode = recorder.finish()
    steps, _ = episode_spec(3, 2, {"front": (2, 2)}).check_episode(episode)
    assert steps == 4 and recorder.success
    np.testing.assert_array_equal(episode["version"], [-1, 0, 1, 2])
    np.testing.assert_array_equal(episode["terminated"], [0, 0, 0, 1])
    np.testing.assert_array_equal(episode["state"][:, 0], [0, 1, 2, 3, 4])
    assert EpisodeRecorder({"state": np.zeros(3, np.float32)}).finish() is None


def test_staleness_counts_policy_steps_only():
    lag = staleness_of(np.array([RANDOM_VERSION, RANDOM_VERSION, 3, 4, 6]), learner_version=7)
    assert (lag.policy_steps, lag.lag_sum, lag.lag_max) == (3, 4 + 3 + 1, 4)
    assert lag.exceeds(3) and not lag.exceeds(4) and not lag.exceeds(None)
    warmup = staleness_of(np.full(5, RANDOM_VERSION), learner_version=9)
    assert warmup.policy_steps == 0 and not warmup.exceeds(0)


def test_layouts_identity_for_one_shape_padded_with_a_kind_one_hot_otherwise():
    same = policy_layouts([{"kind": "sim_sawyer", "obs_dim": 47, "action_dim": 4}] * 2)
    assert same == [PolicyLayout(obs_dim=47, action_dim=4)] * 2
    state = np.arange(47, dtype=np.float32)
    assert same[0].pad_state(state) is state
    mixed = policy_layouts([{"kind": "sim_so101", "obs_dim": 15, "action_dim": 6},
                            {"kind": "sim_sawyer", "obs_dim": 47, "action_dim": 4}])
    assert [(m.obs_dim, m.action_dim, m.embodiment, m.num_embodiments) for m in mixed] == [(49, 6, 1, 2),
                                                                                         (49, 6, 0, 2)]
    padded = mixed[0].pad_state(np.ones(15, np.float32))
    expected = np.concatenate([np.ones(15), np.zeros(32), [0.0, 1.0]])
    np.testing.assert_array_equal(padded, expected)
    # The learner's mask of executed action entries, read off the one-hot: SO-101 all 6, Sawyer 4.
    assert embodiment_action_mask(same) is None and [m.command_size for m in mixed] == [6, 4]
    mask = embodiment_action_mask(mixed)
    states = torch.from_numpy(np.stack([mixed[0].pad_state(np.ones(15, np.float32)),
                                        mixed[1].pad_state(np.ones(47, np.float32))]))
    assert torch.equal(mask(states), torch.tensor([[1.0] * 6, [1.0] * 4 + [0.0] * 2]))
    assert torch.equal(mask({"state": states}), mask(states))


@pytest.mark.parametrize("action", ["drop", "log"])
def test_learner_drops_or_logs_episodes_past_the_staleness_bound(tmp_path, action):
    from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
    from infinirl.realworld.learner_worker import LearnerLoopSpec, RealWorldLearnerWorker
    from infinirl.realworld.replay import ReplayStore

    loop = LearnerLoopSpec(replay_dir=str(tmp_path / "replay"), learning_starts=8, publish_every=2, max_staleness=1,
                           staleness_action=action, durable=False)
    # No Ray: the component's logic alone, on a real store.
    learner = RealWorldLearnerWorker(SACNetSpec(actor_hidden=(8,), critic_hidden=(8,)), SACUpdateSpec(batch_size=4),
                                     loop, 3, 2)

    def episode(version):
        return {"state": np.zeros((5, 3), np.float32), "action": np.zeros((4, 2), np.float32),
                "reward": np.zeros(4, np.float32), "terminated": np.zeros(4, np.float32),
                "version": np.full(4, version, np.int64)}

    assert learner.add_and_update([episode(-1), episode(-1)], num_updates=6, publish=True) == 4  # 3 + 1 published
    learner.add_and_update([episode(3), episode(2)], num_updates=0)  # lags 1 (kept) and 2 (past the bound)
    status = learner.status()
    assert status["counts"]["stale_episodes"] == 1 and status["counts"]["lag_max"] == 2
    kept = 3 if action == "drop" else 4
    assert status["store_episodes"] == kept and status["counts"].get("dropped_episodes", 0) == 4 - kept
    learner.close()
    store = ReplayStore(str(tmp_path / "replay"), writable=False)
    assert store.num_episodes == kept
    store.close()


def test_pixel_learner_trains_from_stored_frames_and_syncs_the_encoder(tmp_path):
    """network.encoder=cnn: the learner samples the camera fields from the store, its published
    weights carry the encoder, and a robot's actor copy built for the same cameras loads them and
    acts from a frame; a checkpoint resumes the same updates."""
    import torch

    from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
    from infinirl.realworld.learner_worker import LearnerLoopSpec, RealWorldLearnerWorker
    from infinirl.realworld.robot_worker import VERSION_TENSOR, unit_box

    cameras = {"front": (12, 12)}
    net = SACNetSpec(actor_hidden=(8,), critic_hidden=(8,), encoder="cnn", augment_pad=2,
                     encoder_options={"channels": (4,), "strides": (2,), "feature_dim": 6})
    rng = np.random.default_rng(0)

    def episode():
        return {"state": rng.normal(size=(5, 3)).astype(np.float32),
                "pixels.front": rng.integers(0, 256, (5, 12, 12, 3), dtype=np.uint8),
                "action": rng.uniform(-1, 1, (4, 2)).astype(np.float32), "reward": np.ones(4, np.float32),
                "terminated": np.zeros(4, np.float32), "version": np.full(4, -1, np.int64)}

    def learner(folder):
        loop = LearnerLoopSpec(replay_dir=str(folder), learning_starts=8, publish_every=2, durable=False,
                               cameras=cameras)
        return RealWorldLearnerWorker(net, SACUpdateSpec(batch_size=4), loop, 3, 2)

    first = learner(tmp_path / "replay")
    first.add_and_update([episode(), episode(), episode()], num_updates=3, publish=True)
    assert first.status()["updates"] == 3  # each update's encoder read the sampled frames (it has no other input)
    weights = dict(first.weights_for_sync())
    assert any(name.startswith("encoder.") for name in weights)
    robot_actor = net.build_actor(3, unit_box(2), cameras)
    robot_actor.load_state_dict({k: v for k, v in weights.items() if k != VERSION_TENSOR})
    frame = {"state": torch.zeros(1, 3), "pixels.front": torch.zeros(1, 12, 12, 3, dtype=torch.uint8)}
    torch.testing.assert_close(robot_actor.sample(frame, deterministic=True)[0],
                               first.agent.actor.sample(frame, deterministic=True)[0])

    (tmp_path / "ckpt").mkdir()
    first.save_checkpoint(str(tmp_path / "ckpt"))
    first.add_and_update([], num_updates=2)
    expected = [(name, tensor.clone()) for name, tensor in first.agent.named_tensors()]
    first.close()  # one writer per store: the resumed learner reopens it
    resumed = learner(tmp_path / "replay")
    resumed.load_checkpoint(str(tmp_path / "ckpt"))
    resumed.add_and_update([], num_updates=2)
    for (name, x), (_, y) in zip(expected, resumed.agent.named_tensors()):
        assert torch.equal(x, y), name
    resumed.close()


def test_training_metrics_per_robot_kind_only_with_several_kinds():
    from infinirl.runners.realworld_sac import _per_kind

    def robot(kind, *episodes):
        return {"kind": kind, "episodes": [{"success": s, "return": r} for s, r in episodes]}

    assert _per_kind([robot("sim_sawyer", (1, 2.0))]) == {}  # one kind: the run-wide metrics say it all
    metrics = _per_kind([robot("sim_sawyer", (1, 2.0), (0, -1.0)), robot("sim_so101", (0, -4.0)),
                         robot("sim_sawyer", (1, 5.0))])
    assert metrics == {"rollout/sim_sawyer/success_rate": pytest.approx(2 / 3),
                       "rollout/sim_sawyer/episode_return_mean": pytest.approx(2.0),
                       "rollout/sim_so101/success_rate": 0.0, "rollout/sim_so101/episode_return_mean": -4.0}


def test_a_crash_between_the_demo_and_episode_appends_loses_and_doubles_nothing(tmp_path, monkeypatch):
    from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
    from infinirl.realworld.learner_worker import SOURCE_ID, LearnerLoopSpec, RealWorldLearnerWorker
    from infinirl.realworld.replay import ReplayStore

    loop = LearnerLoopSpec(replay_dir=str(tmp_path / "replay"), demo_dir=str(tmp_path / "demos"), learning_starts=8,
                           interventions=True, interventions_as_demos=True, durable=False)
    learner = RealWorldLearnerWorker(SACNetSpec(actor_hidden=(8,), critic_hidden=(8,)), SACUpdateSpec(batch_size=4),
                                     loop, 3, 2)
    episode = {"state": np.arange(21, dtype=np.float32).reshape(7, 3), "action": np.ones((6, 2), np.float32),
               "reward": np.zeros(6, np.float32), "terminated": np.zeros(6, np.float32),
               "version": np.full(6, -1, np.int64), "intervened": np.array([0, 1, 1, 0, 1, 0], np.float32),
               SOURCE_ID: "edge-a-0-7"}
    real_append = learner.store.append

    def dies(*args, **kwargs):  # the process dies after the demos' appends, before the episode's
        raise SystemExit("killed")

    monkeypatch.setattr(learner.store, "append", dies)
    with pytest.raises(SystemExit):
        learner._ingest([episode])
    assert learner.demos.num_episodes == 2 and learner.store.num_episodes == 0
    monkeypatch.setattr(learner.store, "append", real_append)
    assert learner._ingest([episode]) == ["edge-a-0-7"]  # the sender's resend
    assert learner._ingest([episode]) == ["edge-a-0-7"]  # and a second one, once it is stored
    assert (learner.demos.num_episodes, learner.store.num_episodes) == (2, 1)
    assert learner.status()["counts"]["intervention_demo_steps"] == 3
    learner.close()
    demos = ReplayStore(str(tmp_path / "demos"), writable=False)
    np.testing.assert_array_equal(demos.episode(0)["state"], episode["state"][1:4])
    np.testing.assert_array_equal(demos.episode(1)["state"], episode["state"][4:6])
    demos.close()


def test_the_learner_keeps_state_statistics_per_robot_kind_and_publishes_them(tmp_path):
    """network.normalize_state with two kinds: every stored episode's states are folded into its
    kind's statistics (demonstrations too), the published weights carry them, and a robot's actor
    copy built for the layout acts as the learner's does."""
    from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
    from infinirl.realworld.learner_worker import LearnerLoopSpec, RealWorldLearnerWorker
    from infinirl.realworld.robot_worker import VERSION_TENSOR, unit_box

    net = SACNetSpec(actor_hidden=(8,), critic_hidden=(8,), normalize_state=True)
    layouts = [PolicyLayout(obs_dim=6, action_dim=2, embodiment=kind, num_embodiments=2, command_size=2)
               for kind in (0, 1)]
    rng = np.random.default_rng(0)

    def episode(kind, scale):
        states = np.stack([layouts[kind].pad_state(rng.normal(size=4 - 2 * kind) * scale) for _ in range(5)])
        return {"state": states.astype(np.float32), "action": rng.uniform(-1, 1, (4, 2)).astype(np.float32),
                "reward": np.ones(4, np.float32), "terminated": np.zeros(4, np.float32),
                "version": np.full(4, -1, np.int64)}

    loop = LearnerLoopSpec(replay_dir=str(tmp_path / "replay"), demo_dir=str(tmp_path / "demos"), learning_starts=4,
                           publish_every=1, durable=False)
    learner = RealWorldLearnerWorker(net, SACUpdateSpec(batch_size=4), loop, 6, 2, embodiments=2)
    demo, robot_0, robot_1 = episode(0, 0.1), episode(0, 0.1), episode(1, 50.0)
    learner.add_demonstrations([demo])
    learner.add_and_update([robot_0, robot_1], num_updates=2, publish=True)
    stats = learner.agent.state_normalizer.stats
    np.testing.assert_allclose(stats[0].mean.numpy()[:4], np.concatenate([demo["state"], robot_0["state"]])[:, :4]
                               .astype(np.float64).mean(0), atol=1e-5)
    np.testing.assert_allclose(stats[1].mean.numpy()[:2], robot_1["state"][:, :2].astype(np.float64).mean(0),
                               rtol=1e-3)
    assert float(stats[1].count) == pytest.approx(5, abs=1e-3)  # kind 1's states alone
    weights = {k: v for k, v in learner.weights_for_sync() if k != VERSION_TENSOR}
    assert any(".stats." in name for name in weights)
    robot = net.build_actor(6, unit_box(2), None, layouts[1].num_embodiments)
    robot.load_state_dict(weights)
    obs = torch.from_numpy(robot_1["state"])
    torch.testing.assert_close(robot.sample(obs, deterministic=True)[0],
                               learner.agent.actor.sample(obs, deterministic=True)[0])
    learner.close()


def test_a_resumed_learner_folds_the_episodes_stored_after_its_checkpoint_into_its_state_statistics(tmp_path):
    """Episodes committed between the checkpoint and the restart are in the store already: their
    resends are skipped, so loading the checkpoint folds them in; the resumed learner's statistics
    and counts are those of a learner that never stopped."""
    from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
    from infinirl.realworld.learner_worker import SOURCE_ID, LearnerLoopSpec, RealWorldLearnerWorker

    net = SACNetSpec(actor_hidden=(8,), critic_hidden=(8,), normalize_state=True)
    rng = np.random.default_rng(0)
    episodes = [{"state": (rng.normal(size=(steps + 1, 3)) * (1 + i)).astype(np.float32),
                 "action": rng.uniform(-1, 1, (steps, 2)).astype(np.float32), "reward": np.ones(steps, np.float32),
                 "terminated": np.zeros(steps, np.float32), "version": np.full(steps, -1, np.int64),
                 SOURCE_ID: f"edge-a-0-{i}"} for i, steps in enumerate([4, 6, 3, 5, 7])]

    def learner(folder):
        loop = LearnerLoopSpec(replay_dir=str(folder), learning_starts=10**6, durable=False)
        return RealWorldLearnerWorker(net, SACUpdateSpec(batch_size=4), loop, 3, 2)

    whole = learner(tmp_path / "whole")
    whole.add_and_update(episodes, num_updates=0)
    first = learner(tmp_path / "replay")
    first.add_and_update(episodes[:2], num_updates=0)
    (tmp_path / "ckpt").mkdir()
    first.save_checkpoint(str(tmp_path / "ckpt"))
    first.add_and_update(episodes[2:4], num_updates=0)  # committed, then the run is killed
    first.close()
    resumed = learner(tmp_path / "replay")
    resumed.load_checkpoint(str(tmp_path / "ckpt"))
    resumed.add_and_update(episodes[2:], num_updates=0)  # the sender resends what it was not told was stored
    assert resumed.status()["counts"]["duplicate_episodes"] == 2
    want, got = whole.agent.state_normalizer.state_dict(), resumed.agent.state_normalizer.state_dict()
    assert want.keys() == got.keys()
    for name in want:
        assert torch.equal(want[name], got[name]), name
    for key in ("episodes", "steps"):
        assert resumed.status()["counts"][key] == whole.status()["counts"][key] == (5 if key == "episodes" else 25)
    whole.close()
    resumed.close()


def test_a_learner_started_without_checkpoint_on_earlier_stores_folds_all_their_states(tmp_path):
    """A learner that starts over on the stores an earlier run left (no checkpoint to resume) samples
    their episodes from its first update on: :meth:`observe_stored` folds every stored state, the
    demonstrations' included (a human's intervened stretch once, with its episode), so its statistics
    are those of the learner that stored them; it refuses to fold twice, after a checkpoint or once
    episodes were stored."""
    from infinirl.components.sac_learner import SACNetSpec, SACUpdateSpec
    from infinirl.realworld.learner_worker import LearnerLoopSpec, RealWorldLearnerWorker
    from infinirl.realworld.robot_worker import VERSION_TENSOR

    rng = np.random.default_rng(1)
    episodes = [{"state": (rng.normal(size=(steps + 1, 3)) * (1 + i) + i).astype(np.float32),
                 "action": rng.uniform(-1, 1, (steps, 2)).astype(np.float32), "reward": np.ones(steps, np.float32),
                 "terminated": np.zeros(steps, np.float32), "version": np.full(steps, -1, np.int64),
                 "intervened": np.zeros(steps, np.float32)}
                for i, steps in enumerate([4, 6, 3, 5])]
    episodes[2]["intervened"][1:3] = 1.0  # a take-over: its stretch also goes into the demonstrations store

    def learner(normalize=True):
        loop = LearnerLoopSpec(replay_dir=str(tmp_path / "replay"), demo_dir=str(tmp_path / "demos"),
                               learning_starts=10**6, durable=False, interventions=True,
                               interventions_as_demos=True)
        net = SACNetSpec(actor_hidden=(8,), critic_hidden=(8,), normalize_state=normalize)
        return RealWorldLearnerWorker(net, SACUpdateSpec(batch_size=4), loop, 3, 2)

    earlier = learner()
    earlier.add_demonstrations(episodes[:1])
    earlier.add_and_update(episodes[1:], num_updates=0)
    assert earlier.demos.num_episodes == 2
    want = earlier.agent.state_normalizer.state_dict()
    earlier.close()

    again = learner()
    assert float(again.agent.state_normalizer.stats[0].count) < 1  # nothing folded until asked (an epsilon prior)
    assert again.observe_stored() == 4  # the scripted demonstration and the three episodes, not the stretch
    got = again.agent.state_normalizer.state_dict()
    for name in want:
        assert torch.equal(want[name], got[name]), name
    published = dict(again.weights_for_sync())  # the robots' copy carries the statistics too
    assert all(torch.equal(published[f"encoder.normalizer.{name}"], got[name]) for name in got)
    assert VERSION_TENSOR in published
    with pytest.raises(RuntimeError, match="count them twice"):
        again.observe_stored()
    again.close()

    stored_first = learner()
    stored_first.add_and_update(episodes[:1], num_updates=0)
    with pytest.raises(RuntimeError, match="count them twice"):
        stored_first.observe_stored()
    stored_first.close()
    plain = learner(normalize=False)  # no statistics: nothing to read
    assert plain.observe_stored() == 0
    plain.close()
