"""The pure parts of human interventions against slow references: intervention counts and rates,
intervened stretches as demonstrations, the human reward and success labels, HG-DAgger's aggregate
and its behaviour-cloning loss (float64 references, masks)."""

import math
import os

import numpy as np
import pytest
import torch

from infinirl.realworld.episodes import EpisodeRecorder, episode_spec
from infinirl.realworld.intervention.dagger import AggregateDataset, bc_loss, human_labelled
from infinirl.realworld.intervention.human_reward import SuccessLabelWriter, human_reward, success_labels
from infinirl.realworld.intervention.metrics import InterventionStats, intervention_metrics, intervention_stats
from infinirl.realworld.intervention.segments import intervened_runs, intervened_segments


def reference_runs(flags):
    runs, start = [], None
    for i, flag in enumerate(list(flags) + [0]):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            runs.append((start, i))
            start = None
    return runs


@pytest.mark.parametrize("seed", range(5))
def test_stats_and_runs_match_a_loop(seed):
    flags = (np.random.default_rng(seed).random(37) < 0.4).astype(np.float32)
    runs = reference_runs(flags)
    assert intervened_runs(flags) == runs
    stats = intervention_stats(flags)
    assert stats == InterventionStats(steps=37, intervened_steps=int(flags.sum()), takeovers=len(runs))
    assert stats.rate == pytest.approx(flags.sum() / 37)


def test_stats_of_edge_cases():
    assert intervention_stats(np.zeros(0)).rate == 0.0
    assert intervention_stats(np.ones(4)).takeovers == 1
    assert intervened_runs(np.array([1, 0, 1])) == [(0, 1), (2, 3)]


def test_intervention_metrics_pool_steps_over_episodes():
    episodes = [InterventionStats(steps=10, intervened_steps=5, takeovers=2),
                InterventionStats(steps=30, intervened_steps=0, takeovers=0)]
    metrics = intervention_metrics(episodes)
    assert metrics == {"intervention/rate": 5 / 40, "intervention/episode_rate": 0.5,
                       "intervention/takeovers_per_episode": 1.0, "intervention/steps": 5.0}
    assert intervention_metrics([]) == {}


def make_episode(flags, cameras=False):
    steps = len(flags)
    episode = {"state": np.arange((steps + 1) * 2, dtype=np.float32).reshape(steps + 1, 2),
               "action": np.arange(steps * 3, dtype=np.float32).reshape(steps, 3),
               "reward": np.arange(steps, dtype=np.float32), "terminated": np.zeros(steps, np.float32),
               "version": np.full(steps, 7, np.int64), "intervened": np.asarray(flags, np.float32)}
    if cameras:
        episode["pixels.top"] = np.zeros((steps + 1, 2, 2, 3), np.uint8)
    return episode


def test_segments_are_episodes_of_the_intervened_steps():
    episode = make_episode([0, 1, 1, 0, 0, 1], cameras=True)
    first, second = intervened_segments(episode)
    np.testing.assert_array_equal(first["state"], episode["state"][1:4])  # next state of the last step included
    np.testing.assert_array_equal(first["action"], episode["action"][1:3])
    np.testing.assert_array_equal(first["reward"], [1, 2])
    assert first["pixels.top"].shape[0] == 3 and first["version"].tolist() == [7, 7]
    np.testing.assert_array_equal(second["state"], episode["state"][5:7])
    assert second["intervened"].tolist() == [1.0]
    spec = episode_spec(2, 3, {"top": (2, 2)}, interventions=True)
    for segment in (first, second):  # each is a valid replay-store episode
        spec.check_episode(segment)
        assert set(segment) == set(episode)
    assert intervened_segments(make_episode([0, 0])) == []


def test_human_reward_and_labels():
    assert human_reward(()) is None
    success = human_reward(("failure", "success"))  # the last mark counts
    assert success.reward == 1.0 and success.terminated and success.success
    failure = human_reward(("failure",))
    assert failure.reward == 0.0 and failure.terminated and not failure.success
    with pytest.raises(ValueError, match="unknown episode mark"):
        human_reward(("done",))
    assert success_labels(4, "success").tolist() == [0, 0, 0, 1]
    assert success_labels(3, "failure").tolist() == [0, 0, 0]


def test_label_writer_saves_observations_with_labels(tmp_path):
    writer = SuccessLabelWriter(str(tmp_path), prefix="rank0")
    observations = {"state": [np.full(2, i, np.float32) for i in range(3)],
                    "pixels.top": [np.full((2, 2, 3), i, np.uint8) for i in range(3)]}
    path = writer.write(observations, "success")
    with np.load(path) as saved:
        assert saved["label"].tolist() == [0, 0, 1]
        assert saved["state"][:, 0].tolist() == [0, 1, 2] and saved["pixels.top"].shape == (3, 2, 2, 3)
    writer.write(observations, "failure")
    assert SuccessLabelWriter(str(tmp_path), prefix="rank0").count == 2  # a restarted writer adds to them


def test_label_writer_never_overwrites_after_a_file_was_deleted(tmp_path):
    observations = {"state": [np.full(2, i, np.float32) for i in range(2)]}
    writer = SuccessLabelWriter(str(tmp_path), prefix="rank0")
    first, second = writer.write(observations, "success"), writer.write(observations, "failure")
    os.unlink(first)  # a person removed a wrong label
    (tmp_path / "rank0-notanumber.npz").write_bytes(b"")
    restarted = SuccessLabelWriter(str(tmp_path), prefix="rank0")
    assert restarted.count == 2  # after the highest index, not the number of files
    third = restarted.write(observations, "success")
    with np.load(second) as saved:
        assert saved["label"].tolist() == [0, 0]  # still the failure
    # Another writer took the next name meanwhile: skipped, not replaced.
    taken = tmp_path / "rank0-000003.npz"
    taken.write_bytes(b"other")
    fourth = restarted.write(observations, "success")
    assert taken.read_bytes() == b"other" and os.path.basename(fourth) == "rank0-000004.npz"
    assert os.path.basename(third) == "rank0-000002.npz"
    assert sorted(os.listdir(tmp_path)) == ["rank0-000001.npz", "rank0-000002.npz", "rank0-000003.npz",
                                            "rank0-000004.npz", "rank0-notanumber.npz"]  # no temporaries left


def test_background_label_writer_writes_off_the_callers_thread_and_raises_a_failed_write(tmp_path, monkeypatch):
    import threading

    from infinirl.realworld.intervention import human_reward as module

    threads = []
    write = module.SuccessLabelWriter.write

    def recording_write(self, observations, mark):
        threads.append(threading.current_thread().name)
        return write(self, observations, mark)

    monkeypatch.setattr(module.SuccessLabelWriter, "write", recording_write)
    writer = module.BackgroundLabelWriter(str(tmp_path), prefix="rank0")
    observations = {"state": [np.full(2, i, np.float32) for i in range(3)]}
    writer.submit(observations, "success")
    observations["state"].append(np.full(2, 9, np.float32))  # the episode goes on after its mark
    writer.submit({"state": observations["state"][:2]}, "failure")
    writer.close()
    assert threads == ["labels-rank0", "labels-rank0"] and threading.current_thread().name not in threads
    with np.load(writer.written[0]) as saved:  # the rows at the mark, not the ones recorded later
        assert saved["label"].tolist() == [0, 0, 1] and saved["state"][:, 0].tolist() == [0, 1, 2]
    assert len(writer.written) == 2

    def failing_write(self, observations, mark):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(module.SuccessLabelWriter, "write", failing_write)
    failing = module.BackgroundLabelWriter(str(tmp_path), prefix="rank1")
    failing.submit(observations, "success")
    with pytest.raises(RuntimeError, match="writing to .* failed: .*No space left"):
        failing.close()


def test_recorder_keeps_the_intervened_flag_and_the_human_mark():
    recorder = EpisodeRecorder({"state": np.zeros(2, np.float32)})
    recorder.add(np.ones(3), {"state": np.ones(2, np.float32)}, 0.0, False, 4, intervened=True)
    recorder.add(np.ones(3), {"state": np.ones(2, np.float32)}, 0.0, False, 4)
    recorder.relabel_last(reward=1.0, terminated=True, success=True)
    episode = recorder.finish(interventions=True)
    assert episode["intervened"].tolist() == [1.0, 0.0]
    assert episode["reward"].tolist() == [0.0, 1.0] and episode["terminated"].tolist() == [0.0, 1.0]
    assert recorder.success
    assert "intervened" not in recorder.finish()  # robots without a device keep the old fields
    assert "intervened" in episode_spec(2, 3, interventions=True).steps
    assert "intervened" not in episode_spec(2, 3).steps


def test_human_labelled_rows_and_the_aggregate():
    episode = make_episode([0, 1, 1, 0])
    states, actions = human_labelled(episode)
    np.testing.assert_array_equal(states, episode["state"][[1, 2]])  # the state each step started from
    np.testing.assert_array_equal(actions, episode["action"][[1, 2]])
    assert len(human_labelled(episode, all_steps=True)[0]) == 4
    with pytest.raises(KeyError, match="intervened"):
        human_labelled({k: v for k, v in episode.items() if k != "intervened"})
    dataset = AggregateDataset(2, 3)
    assert dataset.add(states, actions) == 2 and dataset.add(*human_labelled(episode, all_steps=True)) == 4
    assert len(dataset) == 6
    with pytest.raises(ValueError, match=r"states \[N, 2\]"):
        dataset.add(np.zeros((1, 3)), np.zeros((1, 3)))
    batch_states, batch_actions = dataset.sample(16, torch.Generator().manual_seed(0))
    assert batch_states.shape == (16, 2) and batch_actions.shape == (16, 3)
    copy = AggregateDataset(2, 3)
    copy.load_state_dict(dataset.state_dict())
    np.testing.assert_array_equal(copy.actions, dataset.actions)


def reference_bc(mean, log_std, target, mask, kind):
    total, weight = 0.0, 0.0
    for b in range(mean.shape[0]):
        for a in range(mean.shape[1]):
            m = mask[b, a] if mask.ndim == 2 else mask[b]
            if kind == "mse":
                value = (math.tanh(mean[b, a]) - target[b, a]) ** 2
            else:
                u = math.atanh(min(max(target[b, a], -1 + 1e-4), 1 - 1e-4))
                std = math.exp(log_std[b, a])
                value = 0.5 * ((u - mean[b, a]) / std) ** 2 + log_std[b, a] + 0.5 * math.log(2 * math.pi)
            total += m * value
            weight += m
    return total / max(weight, 1.0)


@pytest.mark.parametrize("kind", ["mse", "gaussian_nll"])
@pytest.mark.parametrize("mask_kind", ["none", "rows", "entries"])
def test_bc_loss_matches_a_float64_reference(kind, mask_kind):
    rng = np.random.default_rng(3)
    mean, log_std = rng.normal(size=(6, 3)), rng.normal(scale=0.5, size=(6, 3))
    target = np.clip(rng.normal(size=(6, 3)), -1, 1)
    target[0, 0] = 1.0  # a saturated target stays finite
    mask = {"none": np.ones((6, 3)), "rows": (rng.random(6) < 0.5).astype(float),
            "entries": (rng.random((6, 3)) < 0.5).astype(float)}[mask_kind]
    got = bc_loss(torch.tensor(mean, dtype=torch.float64), torch.tensor(log_std, dtype=torch.float64),
                  torch.tensor(target, dtype=torch.float64),
                  None if mask_kind == "none" else torch.tensor(mask), kind=kind)
    assert float(got) == pytest.approx(reference_bc(mean, log_std, target, mask, kind), rel=1e-9)


def test_bc_loss_gradient_reaches_only_masked_in_rows():
    mean = torch.zeros(2, 1, requires_grad=True)
    bc_loss(mean, torch.zeros(2, 1), torch.tensor([[0.5], [0.5]]), torch.tensor([1.0, 0.0])).backward()
    assert mean.grad[0, 0] != 0 and mean.grad[1, 0] == 0
    with pytest.raises(ValueError, match="bc loss"):
        bc_loss(mean, mean, mean, kind="l1")


@pytest.mark.parametrize("loss", ["mse", "gaussian_nll"])
def test_bc_learner_clones_labelled_actions_and_publishes_versions(loss, tmp_path):
    """The learner's own code (no Ray: only rank-free methods run): aggregate, train, checkpoint."""
    from infinirl.components.sac_learner import SACNetSpec
    from infinirl.realworld.intervention.bc_learner import BCLearnerWorker, BCSpec
    from infinirl.realworld.robot_worker import VERSION_TENSOR

    rng = np.random.default_rng(0)
    states = rng.uniform(-1, 1, (65, 2)).astype(np.float32)
    episode = {"state": states, "action": np.clip(0.8 * states[:64, ::-1], -1, 1).astype(np.float32),
               "intervened": (rng.random(64) < 0.5).astype(np.float32)}
    learner = BCLearnerWorker(SACNetSpec(actor_hidden=(32, 32), critic_hidden=(8,)), BCSpec(loss=loss, lr=3e-3,
                              batch_size=32), obs_dim=2, action_dim=2)
    assert learner.train(10)["version"] == 0  # nothing labelled yet: no update, no version
    before = learner.action_error([episode])
    assert learner.aggregate([episode]) == {"added": int(episode["intervened"].sum()), "size": len(learner.dataset)}
    result = learner.train(400)
    assert result["version"] == 1 and result["updates"] == 400
    assert learner.action_error([episode]) < 0.2 * before
    names = [name for name, _ in learner.weights_for_sync()]
    assert names[-1] == VERSION_TENSOR and "mean.weight" in names
    learner.save_checkpoint(str(tmp_path))
    restored = BCLearnerWorker(SACNetSpec(actor_hidden=(32, 32), critic_hidden=(8,)), BCSpec(loss=loss),
                               obs_dim=2, action_dim=2)
    restored.load_checkpoint(str(tmp_path))
    assert restored.version == 1 and restored.dataset_size() == learner.dataset_size()
    assert restored.action_error([episode]) == learner.action_error([episode])
