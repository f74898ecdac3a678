"""LeRobotDataset v3.0 writer and reader: round trip, the on-disk layout LeRobot's loader reads,
file roll-over, statistics against float64 references, atomic writes, one-line errors."""

import json

import numpy as np
import pytest

pytest.importorskip("imageio_ffmpeg")
pq = pytest.importorskip("pyarrow.parquet")

from infinirl.data.lerobot_dataset import (  # noqa: E402
    CODEBASE_VERSION,
    INDEX_FEATURES,
    LeRobotDatasetError,
    LeRobotDatasetReader,
    LeRobotDatasetWriter,
    passthrough_params,
)

SIZE = 64
FPS = 30  # frame times such as 11/30 s have no exact decimal: seeking must still land on the frame
VIDEO = "observation.images.top"
FEATURES = {
    "observation.state": {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]},
    "action": {"dtype": "float32", "shape": (2,), "names": None},
    "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
    "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    VIDEO: {"dtype": "video", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]},
}

# Episode-level columns LeRobot 0.4's loader and writer read from meta/episodes/*.parquet.
LEROBOT_EPISODE_COLUMNS = [
    "episode_index", "tasks", "length", "data/chunk_index", "data/file_index", "dataset_from_index",
    "dataset_to_index", f"videos/{VIDEO}/chunk_index", f"videos/{VIDEO}/file_index",
    f"videos/{VIDEO}/from_timestamp", f"videos/{VIDEO}/to_timestamp", "meta/episodes/chunk_index",
    "meta/episodes/file_index",
]


def synthetic_frames(length: int, phase: int) -> np.ndarray:
    """Smooth colour fields (what H.264 keeps well) with a bright square that jumps every frame,
    so each frame differs clearly from its neighbours and a shifted decode is caught."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    frames = []
    for t in range(length):
        red = 120 + 50 * np.sin(xx / 13 + (t + phase) / 9)
        green = 120 + 50 * np.cos(yy / 17 - (t + phase) / 7)
        blue = np.full_like(red, 90.0 + 2 * t)
        frame = np.stack([red, green, blue], -1)
        row, col = 8 + (7 * (t + phase)) % 40, 8 + (11 * (t + phase)) % 40
        frame[row:row + 12, col:col + 12] = 235.0
        frames.append(frame.clip(0, 255).astype(np.uint8))
    return np.stack(frames)


def synthetic_episode(length: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "observation.state": rng.normal(size=(length, 3)).astype(np.float32),
        "action": rng.uniform(-1, 1, size=(length, 2)).astype(np.float32),
        "next.reward": rng.normal(size=length).astype(np.float32),
        "next.done": np.arange(length) == length - 1,
        VIDEO: synthetic_frames(length, phase=10 * seed),
    }


EPISODES = [(11, "pick up the cube"), (9, "open the drawer"), (7, "pick up the cube")]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Three episodes (two tasks) written once; tests read the folder and never change it."""
    root = tmp_path_factory.mktemp("lerobot") / "ds"
    episodes = [synthetic_episode(length, seed) for seed, (length, _) in enumerate(EPISODES)]
    with LeRobotDatasetWriter(root, fps=FPS, features=FEATURES, robot_type="toy") as writer:
        for episode, (_, task) in zip(episodes, EPISODES):
            writer.add_episode(episode, task=task)
    return root, episodes


def test_round_trip_is_exact_for_numbers_and_close_for_video(dataset):
    root, episodes = dataset
    reader = LeRobotDatasetReader(root)
    assert (len(reader), reader.num_episodes, reader.fps) == (27, 3, FPS)
    assert reader.tasks == ["pick up the cube", "open the drawer"]
    start = 0
    for index, (episode, (length, task)) in enumerate(zip(episodes, EPISODES)):
        got = reader.episode(index)
        assert got["task"] == task
        assert reader.episode_range(index) == (start, start + length)
        for key in ("observation.state", "action", "next.reward", "next.done"):
            np.testing.assert_array_equal(got[key], episode[key].reshape(got[key].shape))
        np.testing.assert_array_equal(got["frame_index"], np.arange(length))
        np.testing.assert_array_equal(got["index"], np.arange(start, start + length))
        np.testing.assert_array_equal(got["episode_index"], np.full(length, index))
        np.testing.assert_allclose(got["timestamp"], np.arange(length) / FPS, rtol=0, atol=1e-6)
        video, source = got[VIDEO].astype(np.float64), episode[VIDEO].astype(np.float64)
        assert got[VIDEO].shape == (length, SIZE, SIZE, 3) and got[VIDEO].dtype == np.uint8
        assert np.abs(video - source).mean() < 3.0, "beyond H.264 noise at crf 18"
        # Each decoded frame is nearest to its own source frame: no frame shifted between episodes.
        errors = np.abs(video[:, None] - source[None]).mean(axis=(2, 3, 4))
        np.testing.assert_array_equal(errors.argmin(axis=1), np.arange(length))
        start += length


def test_frames_by_index_match_the_episode_view(dataset):
    root, _ = dataset
    reader = LeRobotDatasetReader(root, episode_cache=1)
    for index in (0, 10, 11, 19, 26, 3):  # across episodes and back: evicts and re-decodes
        item = reader[index]
        episode = int(item["episode_index"])
        offset = index - reader.episode_range(episode)[0]
        whole = reader.episode(episode)
        assert item["task"] == whole["task"]
        assert item["observation.state"].shape == (3,) and item["timestamp"].shape == ()
        np.testing.assert_array_equal(item[VIDEO], whole[VIDEO][offset])
        np.testing.assert_array_equal(item["action"], whole["action"][offset])
    with pytest.raises(IndexError, match="27 frames"):
        reader[27]


def test_layout_and_metadata_are_what_lerobot_v3_reads(dataset):
    root, _ = dataset
    for path in ("meta/info.json", "meta/stats.json", "meta/tasks.parquet", "meta/episodes/chunk-000/file-000.parquet",
                 "data/chunk-000/file-000.parquet", f"videos/{VIDEO}/chunk-000/file-000.mp4"):
        assert (root / path).is_file(), path
    assert not list(root.parent.glob(".ds.tmp-*")), "the temporary folder was renamed, not left behind"

    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == CODEBASE_VERSION == "v3.0"
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"], info["fps"]) == (3, 27, 2, FPS)
    assert info["splits"] == {"train": "0:3"} and info["robot_type"] == "toy"
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    assert list(info["features"]) == [*FEATURES, *INDEX_FEATURES]
    assert info["features"]["observation.state"] == {"dtype": "float32", "shape": [3], "names": ["x", "y", "z"]}
    assert info["features"]["timestamp"] == {"dtype": "float32", "shape": [1], "names": None}
    video_info = info["features"][VIDEO]["info"]
    assert video_info["video.codec"] == "h264" and video_info["video.pix_fmt"] == "yuv420p"
    assert (video_info["video.height"], video_info["video.width"], video_info["video.fps"]) == (SIZE, SIZE, FPS)

    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert data.column_names == ["observation.state", "action", "next.reward", "next.done", *INDEX_FEATURES]
    state_type = data.schema.field("observation.state").type  # what `datasets` makes of Sequence(length=3)
    assert (state_type.list_size, str(state_type.value_type)) == (3, "float")
    assert str(data.schema.field("next.done").type) == "bool"
    assert [str(data.schema.field(k).type) for k in INDEX_FEATURES] == ["float", "int64", "int64", "int64", "int64"]
    assert data.column("task_index").to_pylist() == [0] * 11 + [1] * 9 + [0] * 7

    episodes = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert all(column in episodes[0] for column in LEROBOT_EPISODE_COLUMNS)
    assert [e["tasks"] for e in episodes] == [[task] for _, task in EPISODES]
    assert [(e["dataset_from_index"], e["dataset_to_index"]) for e in episodes] == [(0, 11), (11, 20), (20, 27)]
    # Episodes follow each other in one video file: each starts where the previous one ended.
    assert [(e[f"videos/{VIDEO}/from_timestamp"], e[f"videos/{VIDEO}/to_timestamp"]) for e in episodes] == [
        (0.0, 11 / FPS), (11 / FPS, 20 / FPS), (20 / FPS, 27 / FPS)]
    second_actions = synthetic_episode(9, 1)["action"].astype(np.float64)
    assert episodes[1]["stats/action/mean"] == pytest.approx(second_actions.mean(0).tolist(), rel=1e-12)

    tasks = pq.read_table(root / "meta/tasks.parquet")
    assert tasks.schema.pandas_metadata["index_columns"] == ["__index_level_0__"]  # pandas reads it as the index
    assert tasks.column("__index_level_0__").to_pylist() == ["pick up the cube", "open the drawer"]
    assert tasks.column("task_index").to_pylist() == [0, 1]


def test_stats_match_float64_references(dataset):
    root, episodes = dataset
    stats = LeRobotDatasetReader(root).stats
    actions = np.concatenate([e["action"] for e in episodes]).astype(np.float64)
    np.testing.assert_allclose(stats["action"]["mean"], actions.mean(0), rtol=1e-12)
    np.testing.assert_allclose(stats["action"]["std"], actions.std(0), rtol=1e-10)
    np.testing.assert_array_equal(stats["action"]["min"], actions.min(0))
    np.testing.assert_array_equal(stats["action"]["max"], actions.max(0))
    assert stats["action"]["count"].tolist() == [27]
    np.testing.assert_allclose(stats["index"]["mean"], [13.0])
    # Images: per channel over all pixels of the sampled frames (here all: fewer than 100), in [0, 1].
    pixels = np.concatenate([e[VIDEO] for e in episodes]).reshape(-1, 3) / 255.0
    assert stats[VIDEO]["mean"].shape == (3, 1, 1)
    np.testing.assert_allclose(stats[VIDEO]["mean"].ravel(), pixels.mean(0), rtol=1e-10)
    np.testing.assert_allclose(stats[VIDEO]["std"].ravel(), pixels.std(0), rtol=1e-10)
    assert set(stats["action"]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}


def test_files_roll_over_with_right_chunk_and_file_indices(tmp_path):
    root = tmp_path / "rolled"
    episodes = [synthetic_episode(length, seed) for seed, length in enumerate((5, 4, 6))]
    # Limits so small that every episode opens a new file; two files per chunk folder.
    with LeRobotDatasetWriter(root, fps=FPS, features=FEATURES, chunks_size=2, data_files_size_in_mb=1e-6,
                              video_files_size_in_mb=1e-6) as writer:
        for episode in episodes:
            writer.add_episode(episode, task="t")
    expected = [(0, 0), (0, 1), (1, 0)]
    rows = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [(r["data/chunk_index"], r["data/file_index"]) for r in rows] == expected
    assert [(r[f"videos/{VIDEO}/chunk_index"], r[f"videos/{VIDEO}/file_index"]) for r in rows] == expected
    assert [r[f"videos/{VIDEO}/from_timestamp"] for r in rows] == [0.0, 0.0, 0.0]
    for chunk, file in expected:
        assert (root / f"data/chunk-{chunk:03d}/file-{file:03d}.parquet").is_file()
        assert (root / f"videos/{VIDEO}/chunk-{chunk:03d}/file-{file:03d}.mp4").is_file()
    reader = LeRobotDatasetReader(root)
    assert len(reader) == 15
    for index, episode in enumerate(episodes):
        got = reader.episode(index)
        np.testing.assert_array_equal(got["action"], episode["action"])
        assert np.abs(got[VIDEO].astype(float) - episode[VIDEO]).mean() < 3.0


def test_writes_are_atomic_and_existing_datasets_are_kept(tmp_path):
    root = tmp_path / "ds"
    with pytest.raises(RuntimeError, match="boom"):
        with LeRobotDatasetWriter(root, fps=FPS, features=FEATURES) as writer:
            writer.add_episode(synthetic_episode(3, 0), task="t")
            raise RuntimeError("boom")
    assert not root.exists() and list(tmp_path.iterdir()) == [], "an interrupted dataset leaves nothing behind"

    with LeRobotDatasetWriter(root, fps=FPS, features=FEATURES) as writer:
        writer.add_episode(synthetic_episode(3, 0), task="first")
    with pytest.raises(LeRobotDatasetError, match="already exists.*overwrite"):
        LeRobotDatasetWriter(root, fps=FPS, features=FEATURES)
    with LeRobotDatasetWriter(root, fps=FPS, features=FEATURES, overwrite=True) as writer:
        writer.add_episode(synthetic_episode(4, 1), task="second")
    assert LeRobotDatasetReader(root).tasks == ["second"] and len(LeRobotDatasetReader(root)) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_bad_episodes_and_features_are_refused_in_one_line(tmp_path):
    with pytest.raises(LeRobotDatasetError, match="even height and width"):
        LeRobotDatasetWriter(tmp_path / "a", fps=FPS, features={VIDEO: {"dtype": "video", "shape": (63, 64, 3)}})
    with pytest.raises(LeRobotDatasetError, match="written by the writer itself"):
        LeRobotDatasetWriter(tmp_path / "a", fps=FPS, features={"index": {"dtype": "int64", "shape": (1,)}})
    with pytest.raises(LeRobotDatasetError, match="dtype 'string'"):
        LeRobotDatasetWriter(tmp_path / "a", fps=FPS, features={"x": {"dtype": "string", "shape": (1,)}})
    writer = LeRobotDatasetWriter(tmp_path / "b", fps=FPS, features=FEATURES)
    episode = synthetic_episode(3, 0)
    with pytest.raises(LeRobotDatasetError, match=r"missing features \['action'\]"):
        writer.add_episode({k: v for k, v in episode.items() if k != "action"}, task="t")
    with pytest.raises(LeRobotDatasetError, match="'observation.state' has frames of shape \\(4,\\)"):
        writer.add_episode({**episode, "observation.state": np.zeros((3, 4), np.float32)}, task="t")
    with pytest.raises(LeRobotDatasetError, match="same number"):
        writer.add_episode({**episode, "action": np.zeros((2, 2), np.float32)}, task="t")
    with pytest.raises(LeRobotDatasetError, match="task must be a non-empty string"):
        writer.add_episode(episode, task="")
    with pytest.raises(LeRobotDatasetError, match="no episodes were added"):
        writer.finalize()
    assert not (tmp_path / "b").exists()


def _copy(dataset_root, tmp_path):
    import shutil

    target = tmp_path / "copy"
    shutil.copytree(dataset_root, target)
    return target


def _one_line_error(root) -> str:
    with pytest.raises(LeRobotDatasetError) as caught:
        LeRobotDatasetReader(root).episode(0)
    message = str(caught.value)
    assert "\n" not in message
    return message


def test_reader_errors_name_the_file_and_the_fix(dataset, tmp_path):
    root, _ = dataset
    assert "meta/info.json not found" in _one_line_error(tmp_path / "nowhere")

    corrupt = _copy(root, tmp_path / "a")
    (corrupt / "meta/info.json").write_text("{not json")
    message = _one_line_error(corrupt)
    assert str(corrupt / "meta/info.json") in message and "not valid JSON" in message

    old = _copy(root, tmp_path / "b")
    info = json.loads((old / "meta/info.json").read_text())
    (old / "meta/info.json").write_text(json.dumps({**info, "codebase_version": "v2.1"}))
    message = _one_line_error(old)
    assert "codebase_version 'v2.1' is not supported" in message and "convert_dataset_v21_to_v30" in message

    no_video = _copy(root, tmp_path / "c")
    video = no_video / f"videos/{VIDEO}/chunk-000/file-000.mp4"
    video.unlink()
    message = _one_line_error(no_video)
    assert f"video {video} " in message and "is missing" in message

    truncated = _copy(root, tmp_path / "d")
    video = truncated / f"videos/{VIDEO}/chunk-000/file-000.mp4"
    video.write_bytes(video.read_bytes()[: video.stat().st_size // 3])
    message = _one_line_error(truncated)
    assert str(video) in message and "re-create the dataset" in message


@pytest.mark.parametrize(("version", "params"), [
    ("9.0.2", ["-fps_mode", "passthrough"]),
    ("5.1", ["-fps_mode", "passthrough"]),
    ("n6.1-static", ["-fps_mode", "passthrough"]),
    ("4.2.2-static", ["-vsync", "passthrough"]),
    ("5.0.1", ["-vsync", "passthrough"]),
    ("N-112345-gdeadbeef", ["-fps_mode", "passthrough"]),  # a git build: recent
])
def test_reader_keeps_every_frame_with_old_and_new_ffmpeg(version, params):
    assert passthrough_params(version) == params
