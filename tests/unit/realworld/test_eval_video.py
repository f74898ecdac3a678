"""The robot's evaluation video: deterministic episodes filmed by its first camera, one frame per
control step plus the last state, into an mp4 that plays at the control rate; taken between
training episodes while the control loop runs; a robot without a camera records nothing and says why."""

import importlib.util

import numpy as np
import pytest

pytest.importorskip("metaworld")

from infinirl.config import to_dataclass  # noqa: E402
from infinirl.realworld.control_loop import RobotControlLoop  # noqa: E402
from infinirl.runners.realworld_sac import env_spec_of, net_spec_of, robot_setup_of  # noqa: E402
from infinirl.runners.realworld_sac_config import RealWorldSACConfig  # noqa: E402
from tests.unit.realworld.running_loop import run_async  # noqa: E402

needs_ffmpeg = pytest.mark.skipif(importlib.util.find_spec("imageio_ffmpeg") is None, reason="needs imageio-ffmpeg")
STEPS = 6


def a_loop(tmp_path, image_size):
    cfg = to_dataclass(RealWorldSACConfig, {
        "output_dir": str(tmp_path / "run"),
        "robot": {"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 50.0, "image_size": image_size}},
        "task": {"max_episode_steps": STEPS}, "network": {"actor_hidden": [16], "critic_hidden": [16]}})
    return RobotControlLoop(robot_setup_of(cfg), env_spec_of(cfg), net_spec_of(cfg), seed=0)


def frames_of(path):
    import imageio.v2 as imageio

    with imageio.get_reader(path, format="FFMPEG") as reader:
        fps = reader.get_meta_data()["fps"]
    return fps, np.stack(imageio.mimread(path))


@needs_ffmpeg
def test_two_episodes_filmed_at_the_control_rate(tmp_path):
    loop = a_loop(tmp_path, image_size=32)
    try:
        result = loop.record_video(2, str(tmp_path / "eval.mp4"))
    finally:
        loop.close()
    assert result["path"] == str(tmp_path / "eval.mp4") and result["frames"] == 2 * (STEPS + 1)
    fps, frames = frames_of(result["path"])
    assert fps == 50 and frames.shape == (2 * (STEPS + 1), 32, 32, 3)
    assert frames.std() > 0  # the scene, not a blank frame
    assert loop.counts["episodes"] == 0  # evaluation episodes are not training episodes


@needs_ffmpeg
def test_filmed_between_training_episodes_while_the_loop_runs(tmp_path):
    loop = a_loop(tmp_path, image_size=32)
    sent, result, _ = run_async(loop, 1, 30, lambda: loop.record_video(1, str(tmp_path / "eval.mp4"), fps=10))
    assert sent and result["frames"] == STEPS + 1 and frames_of(result["path"])[0] == 10
    assert all(len(episode["action"]) <= STEPS for episode in sent)  # no filmed step leaked into training


def test_a_robot_without_a_camera_records_nothing_and_says_why(tmp_path):
    loop = a_loop(tmp_path, image_size=None)
    try:
        result = loop.record_video(1, str(tmp_path / "eval.mp4"))
    finally:
        loop.close()
    assert result == {"skipped": "sim_sawyer has no camera (a simulated robot renders one with "
                                 "robot.options.image_size)"}
    assert not (tmp_path / "eval.mp4").exists()
