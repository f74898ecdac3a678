"""The success classifier: the labels folder as SuccessLabelWriter writes it, the episode split and
the balanced batches (exact), the metrics against a float64 count by hand, training on a separable
dataset, the save / load round trip, and every bad input as one line naming the file and the fix."""

import json

import numpy as np
import pytest
import torch

from infinirl.cli import main
from infinirl.realworld.intervention.human_reward import SuccessLabelWriter
from infinirl.realworld.robot_env import RobotEnvSpec
from infinirl.realworld.success_classifier import (
    ClassifierSpec,
    TrainSpec,
    balanced_batch,
    classification_metrics,
    load_classifier,
    load_labels,
    save_classifier,
    split_episodes,
    train_classifier,
)


def write_episodes(folder, successes, failures, steps=6, seed=0, image_size=None):
    """Episodes of a 3-entry state far from the success region (|x| < 0.4) until, in a success
    episode, the marked last one at x[0] + x[1] >= 1.2 (a margin: separable); frames, when asked
    for, are dark except at the success."""
    rng = np.random.default_rng(seed)
    writer = SuccessLabelWriter(str(folder), prefix="rank0")
    for mark in ["success"] * successes + ["failure"] * failures:
        states = list(rng.uniform(-0.4, 0.4, (steps, 3)).astype(np.float32))
        if mark == "success":
            states[-1] = np.array([0.6 + rng.uniform(0, 0.4), 0.6 + rng.uniform(0, 0.4), rng.uniform(-1, 1)],
                                  np.float32)
        observations = {"state": states}
        if image_size:
            frames = [rng.integers(0, 60, (image_size, image_size, 3), dtype=np.uint8) for _ in states]
            if mark == "success":
                frames[-1] = rng.integers(190, 255, (image_size, image_size, 3), dtype=np.uint8)
            observations["pixels.front"] = frames
        writer.write(observations, mark)


def test_labels_folder_reads_every_episode_in_order(tmp_path):
    write_episodes(tmp_path, successes=2, failures=1, steps=4)
    data = load_labels(str(tmp_path))
    assert data.files == ("rank0-000000.npz", "rank0-000001.npz", "rank0-000002.npz")
    assert data.shapes == {"state": (3,)}
    assert data.labels.tolist() == [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0]  # the marked (last) observation only
    assert data.episode.tolist() == [0] * 4 + [1] * 4 + [2] * 4
    with np.load(tmp_path / "rank0-000001.npz") as raw:
        np.testing.assert_array_equal(data.obs["state"][4:8], raw["state"])


def test_split_holds_out_whole_episodes_of_each_outcome(tmp_path):
    write_episodes(tmp_path, successes=10, failures=5, steps=3)
    data = load_labels(str(tmp_path))
    train, val = split_episodes(data, 0.2, seed=3)
    assert np.array_equal(np.sort(np.concatenate([train, val])), np.arange(len(data.labels)))
    assert not set(train.tolist()) & set(val.tolist())
    val_episodes = set(data.episode[val].tolist())
    assert not val_episodes & set(data.episode[train].tolist())  # no episode is split across
    assert len(val) == 3 * 3  # round(0.2 * 10) = 2 success episodes + round(0.2 * 5) = 1 failure episode
    assert int(data.labels[val].sum()) == 2
    again, _ = split_episodes(data, 0.2, seed=3)
    assert np.array_equal(train, again)  # seeded
    assert any(not np.array_equal(val, split_episodes(data, 0.2, seed=s)[1]) for s in range(4, 8))
    _, none = split_episodes(data, 0.0)
    assert len(none) == 0
    with pytest.raises(ValueError, match="val_fraction"):
        split_episodes(data, 1.0)


def test_split_keeps_at_least_one_episode_of_a_group_for_training(tmp_path):
    write_episodes(tmp_path, successes=2, failures=1, steps=2)
    data = load_labels(str(tmp_path))
    train, val = split_episodes(data, 0.9, seed=0)
    assert set(data.episode[val].tolist()) <= {0, 1} and len(set(data.episode[val].tolist())) == 1
    assert 2 in set(data.episode[train].tolist())  # the lone failure episode stays in training


def test_balanced_batch_draws_half_of_each_class():
    labels = np.array([0] * 97 + [1] * 3, np.int8)
    rows = np.arange(100)
    batch = balanced_batch(labels, rows, 9, np.random.default_rng(0))
    assert len(batch) == 9 and int(labels[batch].sum()) == 4  # half, rounded down, are successes
    assert set(batch[labels[batch] == 1].tolist()) <= {97, 98, 99}
    with pytest.raises(ValueError, match="both classes"):
        balanced_batch(labels, np.arange(97), 8, np.random.default_rng(0))


def test_metrics_match_a_count_by_hand():
    predicted = np.array([1, 1, 0, 0, 1, 0, 0, 0], bool)
    labels = np.array([1, 0, 1, 0, 1, 0, 0, 0])
    m = classification_metrics(predicted, labels)
    tp, fp, tn, fn = 2.0, 1.0, 4.0, 1.0
    assert (m["tp"], m["fp"], m["tn"], m["fn"]) == (tp, fp, tn, fn)
    assert m["accuracy"] == (tp + tn) / 8 and m["precision"] == tp / (tp + fp) and m["recall"] == tp / (tp + fn)
    assert m["balanced_accuracy"] == (tp / (tp + fn) + tn / (tn + fp)) / 2
    none = classification_metrics(np.zeros(3, bool), np.zeros(3))
    assert np.isnan(none["precision"]) and np.isnan(none["recall"]) and none["balanced_accuracy"] == 1.0


def test_mlp_learns_a_separable_set_and_round_trips(tmp_path):
    write_episodes(tmp_path / "labels", successes=30, failures=10, steps=8)
    data = load_labels(str(tmp_path / "labels"))
    spec = ClassifierSpec(hidden=(32, 32))
    classifier, report = train_classifier(data, spec, TrainSpec(steps=300, seed=1))
    assert report["validation"]["balanced_accuracy"] == 1.0 and report["train"]["balanced_accuracy"] == 1.0
    assert report["successes"] == 30 and report["episodes"] == 40
    same, _ = train_classifier(data, spec, TrainSpec(steps=300, seed=1))
    for a, b in zip(classifier.state_dict().values(), same.state_dict().values()):
        assert torch.equal(a, b)  # seeded: the same weights

    path = str(tmp_path / "model" / "classifier.pt")
    save_classifier(path, classifier, report)
    loaded = load_classifier(path, {"state": (3,)})
    probe = {"state": np.random.default_rng(5).uniform(-1, 1, (50, 3)).astype(np.float32)}
    np.testing.assert_array_equal(loaded.probability(probe), classifier.probability(probe))
    assert loaded.spec == spec and loaded.threshold == 0.5 and loaded.report["validation"]["tp"] >= 1
    about = json.loads(open(f"{path}.json").read())
    assert about["spec"]["obs_keys"] == ["state"] and about["shapes"] == {"state": [3]}
    assert "state_dict" not in about


def test_cnn_learns_from_frames(tmp_path):
    write_episodes(tmp_path, successes=12, failures=4, steps=4, image_size=36)
    data = load_labels(str(tmp_path), ["pixels.front"])
    spec = ClassifierSpec(architecture="cnn", obs_keys=("pixels.front",), hidden=(16,))
    classifier, report = train_classifier(data, spec, TrainSpec(steps=60, batch_size=16))
    assert report["validation"]["balanced_accuracy"] == 1.0
    with pytest.raises(ValueError, match="use architecture 'cnn'"):
        train_classifier(data, ClassifierSpec(obs_keys=("pixels.front",)), TrainSpec(steps=1))


def test_load_fails_in_one_line_naming_the_file_and_the_fix(tmp_path):
    path = str(tmp_path / "missing.pt")
    with pytest.raises(FileNotFoundError, match="missing.pt does not exist; train one with: infinirl train-classifier"):
        load_classifier(path)
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt is not a success classifier file"):
        load_classifier(str(tmp_path / "other.pt"))
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="junk.pt cannot be read"):
        load_classifier(str(tmp_path / "junk.pt"))
    write_episodes(tmp_path / "labels", successes=4, failures=2, steps=3)
    classifier, report = train_classifier(load_labels(str(tmp_path / "labels")), ClassifierSpec(hidden=(8,)),
                                          TrainSpec(steps=5))
    good = str(tmp_path / "good.pt")
    save_classifier(good, classifier, report)
    with pytest.raises(ValueError, match=r"good.pt reads 'state' of shape \[3\], this robot env gives \[7\]"):
        load_classifier(good, {"state": (7,)})
    with pytest.raises(ValueError, match=r"good.pt reads 'state', which this robot env's observation lacks"):
        load_classifier(good, {"pixels.front": (8, 8, 3)})


def _train_cli(capsys, *args):
    code = main(["train-classifier", *map(str, args)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize("case, expected", [
    ("missing", "does not exist"),
    ("empty", "holds no .npz label files"),
    ("failures_only", "hold no success (every label is 0)"),
    ("one_success", "too few to hold out both classes"),
    ("wrong_key", "has no ['pixels.front']"),
])
def test_train_command_reports_bad_input_in_one_line(tmp_path, capsys, case, expected):
    folder = tmp_path / "labels"
    extra = []
    if case != "missing":
        folder.mkdir()
    if case == "failures_only":
        write_episodes(folder, successes=0, failures=3)
    if case == "one_success":
        write_episodes(folder, successes=1, failures=3)
    if case == "wrong_key":
        write_episodes(folder, successes=3, failures=3)
        extra = ["--keys", "pixels.front"]
    code, _, err = _train_cli(capsys, folder, "--out", tmp_path / "c.pt", *extra)
    assert code == 2 and expected in err and err.count("\n") == 1 and err.startswith("infinirl: train-classifier: ")
    assert not (tmp_path / "c.pt").exists()


def test_train_command_saves_a_classifier(tmp_path, capsys):
    write_episodes(tmp_path / "labels", successes=10, failures=5)
    out = tmp_path / "c.pt"
    code, printed, _ = _train_cli(capsys, tmp_path / "labels", "--out", out, "--steps", 200, "--hidden", "32")
    assert code == 0 and "validation: accuracy" in printed and out.exists()
    assert load_classifier(str(out)).spec.hidden == (32,)


def test_env_spec_checks_the_classifier_reward_options():
    RobotEnvSpec(rewards={"classifier": 1.0}, reward_options={"classifier": {"path": "c.pt", "threshold": 0.7}})
    with pytest.raises(ValueError, match="reward 'classifier' needs reward_options.classifier.path"):
        RobotEnvSpec(rewards={"classifier": 1.0})
    with pytest.raises(ValueError, match=r"reward_options.classifier: unknown \['treshold'\]"):
        RobotEnvSpec(rewards={"classifier": 1.0}, reward_options={"classifier": {"path": "c.pt", "treshold": 0.7}})
    with pytest.raises(ValueError, match="reward_options.success: unknown"):
        RobotEnvSpec(rewards={"success": 1.0}, reward_options={"success": {"path": "c.pt"}})
    with pytest.raises(ValueError, match=r"\['classifier'\] are not among the rewards"):
        RobotEnvSpec(rewards={"success": 1.0}, reward_options={"classifier": {"path": "c.pt"}})
