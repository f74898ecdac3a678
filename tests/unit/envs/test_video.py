"""Eval videos: a whole mp4 or none, and a missing ffmpeg writer named with the fix."""

import importlib.util

import numpy as np
import pytest

from infinirl.envs import video
from infinirl.envs.video import write_mp4

pytest.importorskip("imageio_ffmpeg")


def frames(n=6, size=16):
    return [np.full((size, size, 3), 30 * i, dtype=np.uint8) for i in range(n)]


def test_writes_a_readable_mp4_and_leaves_no_temporary(tmp_path):
    import imageio.v2 as imageio

    path = write_mp4(str(tmp_path / "runs" / "eval.mp4"), frames(), fps=10)
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["eval.mp4"]
    decoded = imageio.mimread(path)
    assert len(decoded) == 6 and decoded[0].shape == (16, 16, 3)


def test_without_ffmpeg_it_names_the_package_and_writes_nothing(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(video.importlib.util, "find_spec",
                        lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    with pytest.raises(RuntimeError, match="pip install imageio-ffmpeg"):
        write_mp4(str(tmp_path / "eval.mp4"), frames())
    assert list(tmp_path.iterdir()) == []


def test_a_failed_encode_leaves_neither_the_video_nor_a_stub(tmp_path, monkeypatch):
    import imageio.v2 as imageio

    def fail(path, *args, **kwargs):
        with open(path, "wb") as handle:  # the encoder got as far as a stub before the disk filled
            handle.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(imageio, "mimsave", fail)
    with pytest.raises(OSError, match="disk full"):
        write_mp4(str(tmp_path / "eval.mp4"), frames())
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def step_count_frames(monkeypatch):
    """Sub-env frames that show how many steps the episode has taken (Pendulum's own frames need
    pygame); and the frames each mp4 would hold, instead of writing it."""
    gymnasium_env = pytest.importorskip("infinirl.envs.gymnasium_env")
    sub_env = gymnasium_env.GymnasiumSubEnv
    reset, step = sub_env.reset, sub_env.step

    def counting_reset(self, *args, **kwargs):
        self.steps_taken = 0
        return reset(self, *args, **kwargs)

    def counting_step(self, *args, **kwargs):
        self.steps_taken += 1
        return step(self, *args, **kwargs)

    monkeypatch.setattr(sub_env, "reset", counting_reset)
    monkeypatch.setattr(sub_env, "step", counting_step)
    monkeypatch.setattr(sub_env, "render", lambda self: np.full((8, 8, 3), self.steps_taken, np.uint8))
    written = {}

    def write_mp4(path, frames, fps=30):
        written[path] = list(frames)
        return path

    monkeypatch.setattr(video, "write_mp4", write_mp4)
    return written


@pytest.mark.parametrize(("episode", "shown"), [(5, [0, 2, 4, 5]), (4, [0, 2, 4])])
def test_an_embodied_video_ends_on_the_episodes_final_frame(step_count_frames, tmp_path, episode, shown):
    """Whatever the frame skip, each episode's last frame (the state it ended in: the success) is
    in the video, once."""
    pytest.importorskip("gymnasium")
    from infinirl.components.embodied_rollout import EmbodiedRolloutWorker, PolicySpec
    from infinirl.components.env_worker import EnvSpec, probe_env_specs
    from infinirl.runtime.worker import RankContext

    spec = EnvSpec(name="gym:Pendulum-v1", num_envs=1, num_workers=0)
    worker = EmbodiedRolloutWorker.__new__(EmbodiedRolloutWorker)
    worker.ctx = RankContext("rollout", 0, 1)
    worker.__init__(spec, PolicySpec(name="mlp_gaussian", options={"hidden": [8]}), *probe_env_specs(spec.name, {}),
                    seed=0, host_env=False)
    try:
        path = str(tmp_path / "eval.mp4")
        result = worker.record_video([0, 1], path, frame_skip=2, max_episode_steps=episode)
    finally:
        worker.close()
    assert [int(frame[0, 0, 0]) for frame in step_count_frames[path]] == shown * 2
    assert result["frames"] == 2 * len(shown) and len(result["episode_success"]) == 2


def test_a_sac_video_ends_on_the_episodes_final_frame(step_count_frames, tmp_path):
    pytest.importorskip("gymnasium")
    from tests.unit.test_sac_collector import make_collector

    collector = make_collector(num_envs=1)
    try:
        path = str(tmp_path / "eval.mp4")
        result = collector.record_video([0], path, frame_skip=2, max_steps=5)
    finally:
        collector.close()
    assert [int(frame[0, 0, 0]) for frame in step_count_frames[path]] == [0, 2, 4, 5]
    assert result["frames"] == 4
