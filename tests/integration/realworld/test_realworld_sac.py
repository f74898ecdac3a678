"""The real-world SAC runner end to end on a simulated Sawyer running in real time: the robot worker
acts at its own rate while the learner updates from the persistent replay store, every step stamped
with the policy version that chose it; a run resumed from an earlier checkpoint reopens the store
with every episode in it and continues; the synchronous mode runs the same components in turns, and
with the simulated arm in lockstep its first iterations are pinned."""

import importlib.util
import json
import re

import numpy as np
import pytest
import torch

# Not imported here: MetaWorld loads MuJoCo, which picks its GL backend once per process, and the
# simulated robots choose a headless one before they import it (tests of cameras share this process).
pytestmark = pytest.mark.skipif(importlib.util.find_spec("metaworld") is None, reason="needs metaworld")

from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.realworld.replay import ReplayStore  # noqa: E402
from infinirl.runners.realworld_sac import run  # noqa: E402
from infinirl.runners.realworld_sac_config import RealWorldSACConfig  # noqa: E402
from tests.integration.pins import check_pinned  # noqa: E402
from tests.integration.resume import killed_after_checkpoint  # noqa: E402


def make_cfg(output_dir, iterations, **extra):
    raw = {
        "iterations": iterations, "output_dir": str(output_dir), "save_every": 1, "keep_checkpoints": 0,
        "loggers": [],
        "robot": {"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 50.0, "image_size": None}},
        "task": {"max_episode_steps": 20},
        "pipeline": {"iteration_s": 3.0, "publish_every": 5, "max_staleness": 0, "staleness_action": "log",
                     "durable": False},
        "network": {"actor_hidden": [32, 32], "critic_hidden": [32, 32]},
        "algorithm": {"batch_size": 32, "learning_starts": 40},
        "eval": {"every": 0, "episodes": 1},
        "cluster": {"log_to_driver": False}, **extra,
    }
    return to_dataclass(RealWorldSACConfig, raw)


def rows_of(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def versions_in(replay):
    store = ReplayStore(str(replay), writable=False)
    try:
        return np.concatenate([store.episode(i)["version"] for i in range(store.num_episodes)]), store.num_episodes
    finally:
        store.close()


def test_async_run_streams_versioned_episodes_and_resumes_with_the_store(ray_cluster, tmp_path):
    first = run(make_cfg(tmp_path / "run", 2))
    assert first["updates"] > 0 and first["version"] >= 1 and first["replay_episodes"] >= 1
    rows = rows_of(tmp_path / "run" / "metrics.jsonl")
    assert [r["step"] for r in rows] == [1, 2]
    last = rows[-1]
    for key in ("pipeline/staleness_mean", "pipeline/staleness_max", "pipeline/stale_episodes",
                "train/updates_per_s", "replay/transitions", "eval/success_rate"):
        assert key in last, key
    assert last["pipeline/version"] >= 1 and last["train/critic_loss"] == last["train/critic_loss"]
    versions, episodes = versions_in(tmp_path / "run" / "replay")
    assert episodes == first["replay_episodes"]
    assert versions.min() == -1  # warm-up: uniform actions before any trained weights arrived
    assert versions.max() >= 1  # then the robot acted with the versions the learner published
    assert np.all(np.diff(versions) >= 0)  # one robot, episodes stored in the order it ran them: versions only grow

    # Killed after iteration 1's checkpoint: the store on disk holds more episodes than that
    # checkpoint saw (those appended later), and the resumed run continues with all of them.
    killed_after_checkpoint(tmp_path / "run", tmp_path / "resumed", 1)
    resumed = run(make_cfg(tmp_path / "resumed", 3))
    assert resumed["replay_episodes"] > first["replay_episodes"]  # nothing appended before the kill is lost
    resumed_rows = rows_of(tmp_path / "resumed" / "metrics.jsonl")
    assert [r["step"] for r in resumed_rows] == [1, 2, 3]
    assert resumed_rows[1]["train/updates"] >= rows[0]["train/updates"]  # updates continue from the checkpoint
    assert resumed_rows[1]["env/steps"] > rows[0]["env/steps"]  # and so do the robots' steps (new workers count from 0)


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_sync_mode_collects_then_updates_with_no_staleness(ray_cluster, tmp_path):
    summary = run(make_cfg(tmp_path / "sync", 1, pipeline={"mode": "sync", "iteration_s": 3.0, "max_staleness": 0,
                                                            "staleness_action": "drop", "durable": False},
                           algorithm={"batch_size": 32, "learning_starts": 40, "utd_ratio": 0.5}))
    row = rows_of(tmp_path / "sync" / "metrics.jsonl")[-1]
    assert row["pipeline/staleness_max"] == 0 and row["pipeline/dropped_episodes"] == 0
    assert summary["updates"] == pytest.approx(0.5 * (row["replay/transitions"] - 40), abs=20)
    versions, _ = versions_in(tmp_path / "sync" / "replay")
    assert versions.max() >= 1


def test_sync_lockstep_run_is_pinned(ray_cluster, tmp_path):
    """A window shorter than any turn: one turn (an episode, then its updates) per iteration. With the
    simulated arm in lockstep (one control period per command) the run is a function of its seeds, so
    its learning metrics are pinned (tests/integration/pins.py); in real time they are not."""
    options = {"task": "reach-v3", "control_hz": 50.0, "image_size": None, "lockstep": True}
    run(make_cfg(tmp_path / "straight", 4, save_every=0, robot={"kind": "sim_sawyer", "options": options},
                 pipeline={"mode": "sync", "iteration_s": 0.001, "durable": False},
                 algorithm={"batch_size": 16, "learning_starts": 20, "utd_ratio": 0.5},
                 eval={"every": 2, "episodes": 1, "video_episodes": 0}))
    rows = rows_of(tmp_path / "straight" / "metrics.jsonl")
    assert [(r["step"], r["rollout/episodes"]) for r in rows] == [(1, 1.0), (2, 1.0), (3, 1.0), (4, 1.0)]
    # The one way wall-clock time still reaches a lockstep run: a step stalled past
    # robot.command_deadline_s makes the watchdog hold the arm and re-base the next command.
    assert all(r["robot/safety_events"] == 0 for r in rows), "a step stalled past the watchdog's deadline"
    check_pinned("realworld_sac", tmp_path / "straight", [
        "rollout/episode_return_mean", "rollout/episode_length_mean", "replay/transitions", "train/critic_loss",
        "train/actor_loss", "train/alpha", "train/q_mean", "eval/return_mean", "eval/success_rate"])


def test_network_sections_build_the_actors_the_robots_act_with(tmp_path):
    from infinirl.models.sac_encoders import EncodedActor
    from infinirl.models.sac_nets import FlowSACActor, SquashedGaussianActor
    from infinirl.realworld.robot_worker import unit_box
    from infinirl.runners.realworld_sac import net_spec_of

    assert isinstance(net_spec_of(make_cfg(tmp_path, 1)).build_actor(5, unit_box(2)), SquashedGaussianActor)
    assert isinstance(net_spec_of(make_cfg(tmp_path, 1, **FLOW)).build_actor(5, unit_box(2)), FlowSACActor)
    pixels = net_spec_of(make_cfg(tmp_path, 1, **PIXELS)).build_actor(5, unit_box(2), {"corner": (32, 32)})
    assert isinstance(pixels, EncodedActor) and list(pixels.encoder.cameras) == ["corner"]
    normed = net_spec_of(make_cfg(tmp_path, 1, network={"actor_hidden": [32], "critic_hidden": [32],
                                                         "layer_norm": True}))
    assert normed.layer_norm
    assert any(isinstance(m, torch.nn.LayerNorm) for m in normed.build_actor(5, unit_box(2)).modules())
    bad_flow = {"network": {**FLOW["network"], "flow": {"num_steps": 2, "hiden": [32]}}}
    with pytest.raises(ConfigError, match="network .actor=flow.*hiden"):  # before any worker (no cluster here)
        run(make_cfg(tmp_path / "bad_flow", 1, **bad_flow))


def test_config_errors_name_the_key_before_any_worker_starts(tmp_path):
    for extra, key in (({"robot": {"kind": "sim_sawyr"}}, "robot.kind"),
                       ({"task": {"rewards": {"sucess": 1.0}}}, "task.rewards"),
                       ({"task": {"observations": ["pixels"]}}, "task.observations"),
                       ({"algorithm": {"batch_size": 64, "learning_starts": 10}}, "algorithm.learning_starts"),
                       ({"demos": {"episodes": 2, "policy": "nope"}}, "demos.policy"),
                       ({"demos": {"episodes": 2, "policy": "metaworld_expert", "options": {"taks": "push-v3"}}},
                        "demos.options.taks: not an option of demo policy 'metaworld_expert'; its options: task"),
                       ({"pipeline": {"mode": "fast"}}, "pipeline.mode"),
                       ({"network": {"encoder": "cnn"}}, "task.cameras"),
                       ({"network": {"encoder": "vit"}}, "network.encoder"),
                       ({"network": {"actor": "flow", "flow": {"noise_method": "flow_sde"}}},
                        "network.flow.noise_method"),
                       ({"network": {"actor": "flow", "flow": {"chunk": 2}}}, "network.flow.chunk"),
                       # driver options: a misspelt key, and a value the driver refuses
                       ({"robot": {"kind": "sim_sawyer", "options": {"control_rate": 20.0}}},
                        "robot.options.control_rate: not an option of robot kind 'sim_sawyer'; its options: task"),
                       ({"robot": {"kind": "sim_so101", "options": {"success": "grasp"}},
                         "task": {"observations": ["proprio"], "rewards": {"success": 1.0}}},
                        "robot.options: sim_so101: success='grasp'; choose one of pick, reach"),
                       ({"robot": {"fleet": [{"kind": "sim_sawyer", "options": {"taks": "reach-v3"}}]}},
                        "robot.fleet[0].options.taks: not an option"),
                       ({"task": {"frame_size": [64]}}, "task.frame_size=[64]: give [height, width]"),
                       ({"task": {"cameras": ["corner"], "camera_names": {"front": "main"}}},
                        "task.camera_names: RobotEnvSpec.camera_names renames ['front']"),
                       ({"robot": {"kind": "sim_sawyer", "options": {"image_size": [48]}}},
                        "image_size must be a positive int or [height, width]")):
        with pytest.raises(ConfigError, match=re.escape(key)):
            make_cfg(tmp_path / "bad", 1, **extra).validate()


def test_counters_continue_from_the_checkpoint_whatever_the_components_counted_before():
    """A resumed run's cumulative counters (``env/steps``, ``robot/late_steps``, the safety layer's and
    the edge link's) go on from its checkpoint's: new robot workers count from 0, and a robot that
    outlived the trainer (an edge node) had counted for the run that was stopped."""
    from infinirl.runners.realworld_sac import RunCounts, robot_counts

    def robot(steps, late, clips, events):
        return {"counts": {"steps": steps, "late_steps": late}, "safety_clips": {"velocity": clips},
                "safety_events": {"watchdog_hold": events}}

    saved = {"env/steps": 100.0, "robot/late_steps": 7.0, "robot/safety_clips": 30.0, "robot/safety_events": 2.0,
             "robot/safety_aborts": 1.0, "link/connects": 3.0}
    for before in (robot(0, 0, 0, 0), robot(35, 4, 9, 1)):
        counts = RunCounts()
        counts.restore(RunCounts.saved({"counts": saved}), robot_counts([before]))
        assert counts.totals == saved
        later = robot(before["counts"]["steps"] + 12, before["counts"]["late_steps"] + 1,
                      before["safety_clips"]["velocity"] + 5, before["safety_events"]["watchdog_hold"])
        # the link's hub starts with the resumed trainer: all it counts is new
        assert counts.update({**robot_counts([later]), "link/connects": 1.0}) == {
            "env/steps": 112.0, "robot/late_steps": 8.0, "robot/safety_aborts": 1.0, "robot/safety_clips": 35.0,
            "robot/safety_events": 2.0, "link/connects": 4.0}
    earlier = RunCounts()  # a checkpoint of an earlier version saved the steps alone
    earlier.restore(RunCounts.saved({"env_steps": 40}), {})
    assert earlier.update(robot_counts([robot(3, 2, 0, 0)])) == {
        "env/steps": 43.0, "robot/late_steps": 2.0, "robot/safety_aborts": 0.0, "robot/safety_clips": 0.0,
        "robot/safety_events": 0.0}
    fresh = RunCounts()
    assert fresh.update(robot_counts([robot(7, 0, 1, 0), robot(0, 0, 0, 0)]))["env/steps"] == 7.0


ROBOT_COUNTERS = ("env/steps", "robot/late_steps", "robot/safety_aborts", "robot/safety_clips", "robot/safety_events")


@pytest.mark.slow  # default-suite budget: RunCounts and observe_stored have unit tests
def test_resumed_counters_continue_and_a_start_without_checkpoint_folds_the_stored_states(ray_cluster, tmp_path,
                                                                                          capsys):
    """Resumed: the robots' counters go on from the checkpoint's (new robot workers count from 0).
    Started over without a checkpoint on the store the earlier runs left: training samples those
    episodes, so the learner's state statistics take them all in first."""
    import torch

    from infinirl.runners.checkpoints import Checkpoints

    out = tmp_path / "run"
    # Absolute targets: the safety layer clips each step's jump to its velocity bound, so every window
    # counts clips (late steps depend on the machine's load and may stay at 0).
    task = {"max_episode_steps": 20, "action_mode": "absolute"}
    pipeline = {"iteration_s": 2.0, "publish_every": 5, "durable": False}
    run(make_cfg(out, 2, task=task, pipeline=pipeline))
    first = rows_of(out / "metrics.jsonl")
    assert first[1]["robot/safety_clips"] > 0
    _, state = Checkpoints(str(out)).latest()
    assert state["flow"]["counts"] == {key: first[1][key] for key in ROBOT_COUNTERS}  # in the checkpoint

    run(make_cfg(out, 3, task=task, pipeline=pipeline))
    again = rows_of(out / "metrics.jsonl")
    assert [r["step"] for r in again] == [1, 2, 3]
    for key in ROBOT_COUNTERS:  # one more window on top of the two the checkpoint counted
        assert again[2][key] >= first[1][key], key
    assert again[2]["robot/safety_clips"] > first[1]["robot/safety_clips"]
    assert again[2]["env/steps"] > first[1]["env/steps"]

    capsys.readouterr()
    network = {"actor_hidden": [32, 32], "critic_hidden": [32, 32], "normalize_state": True}
    run(make_cfg(out, 1, task=task, pipeline=pipeline, network=network, resume=False))
    stored_before = capsys.readouterr().out
    assert f"no checkpoint to resume, but {out / 'replay'} holds" in stored_before
    checkpoint = torch.load(out / "checkpoints" / "iter_000001" / "learner" / "learner.pt", weights_only=False)
    store = ReplayStore(str(out / "replay"), writable=False)
    try:
        stored = checkpoint["store"]["episodes"]
        rows = sum(len(store.episode(i)["state"]) for i in range(stored))
        assert stored > again[2]["replay/episodes"]  # the earlier runs' and this one's
    finally:
        store.close()
    count = checkpoint["agent"]["actor"]["encoder.normalizer.stats.0.count"]
    assert float(count) == pytest.approx(rows, abs=1e-3)  # every stored state, the earlier runs' included


@pytest.mark.slow  # a whole run killed and run again (~90 s); the store's own kill -9 tests are in the unit tier
def test_killed_run_resumes_with_every_stored_episode(tmp_path):
    """kill -9 of the whole run (driver, robot and learner processes) between checkpoints; the same
    command again resumes from the newest checkpoint and keeps every episode the store committed."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "killed"
    command = [sys.executable, "-m", "infinirl.cli", "train", "realworld_sac_sawyer_reach", f"output_dir={out}",
               "loggers=[]", "save_every=1", "pipeline.iteration_s=2", "task.max_episode_steps=20",
               "robot.options.control_hz=50.0", "algorithm.batch_size=32", "algorithm.learning_starts=40",
               "network.actor_hidden=[32,32]", "network.critic_hidden=[32,32]", "pipeline.durable=false",
               "eval.every=0", "eval.episodes=1", "demos.episodes=2", "cluster.log_to_driver=false"]
    first = subprocess.Popen([*command, "iterations=50"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)  # its own process group: the kill takes its Ray processes too
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and first.poll() is None:
            if len(list((out / "checkpoints").glob("iter_*"))) >= 2:
                break
            time.sleep(0.5)
        assert first.poll() is None, "the run ended before it could be killed"
    finally:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(60)
    _, at_kill = versions_in(out / "replay")
    assert at_kill >= 1
    resumed = subprocess.run([*command, "iterations=4"], capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "resumed from" in resumed.stdout
    assert "demonstration episodes" not in resumed.stdout  # none recorded again: the demos store survived
    summary = json.loads(resumed.stdout.strip().splitlines()[-1])
    assert summary["replay_episodes"] >= at_kill  # every committed episode is still there


@pytest.mark.slow  # two real-time simulated arms, one of them rendering
def test_two_embodiments_feed_one_policy_and_one_store(ray_cluster, tmp_path):
    fleet = [{"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 50.0, "image_size": None}},
             {"kind": "sim_so101", "options": {"control_hz": 50.0, "image_size": None},
              "task": {"observations": ["proprio", "block_position", "last_action"],
                       "rewards": {"block_distance": 1.0, "success": 1.0}}}]
    summary = run(make_cfg(tmp_path / "fleet", 1, robot={"fleet": fleet},
                           task={"observations": ["proprio", "sim_state", "last_action"], "max_episode_steps": 20},
                           placement={"robot": "0-1"}, eval={"every": 0, "episodes": 1},
                           network={"actor_hidden": [32, 32], "critic_hidden": [32, 32], "normalize_state": True}))
    assert summary["replay_episodes"] >= 2
    store = ReplayStore(str(tmp_path / "fleet" / "replay"), writable=False)
    try:
        states_per_episode = [store.episode(i)["state"] for i in range(store.num_episodes)]
        states = np.concatenate(states_per_episode)
        actions = np.concatenate([store.episode(i)["action"] for i in range(store.num_episodes)])
    finally:
        store.close()
    # Sawyer: 4 proprio + 39 sim state + 4 last action = 47; SO-101: 6 + 3 + 6 = 15; padded to 47 + a 2-kind one-hot.
    assert states.shape[1] == 49 and actions.shape[1] == 6
    kinds = {tuple(row) for row in states[:, -2:]}
    assert kinds == {(1.0, 0.0), (0.0, 1.0)}  # both robots' steps, each marked with its kind
    sawyer_rows = states[states[:, -2] == 1.0]
    assert np.all(sawyer_rows[:, 47:] == [1.0, 0.0])
    so101_rows = states[states[:, -1] == 1.0]
    assert np.all(so101_rows[:, 15:47] == 0.0)  # zeros between the SO-101's own entries and the one-hot
    # network.normalize_state: the learner's statistics per kind are those of that kind's states among
    # the episodes stored when the checkpoint was taken
    import torch

    checkpoint = torch.load(sorted((tmp_path / "fleet" / "checkpoints").glob("iter_*"))[-1] / "learner" / "learner.pt",
                            weights_only=False)
    actor, stored = checkpoint["agent"]["actor"], checkpoint["store"]["episodes"]
    assert stored >= 2
    seen = states_per_episode[:stored]
    for kind in (0, 1):
        rows = np.concatenate([e[e[:, 47 + kind] == 1.0] for e in seen]).astype(np.float64)
        assert float(actor[f"encoder.normalizer.stats.{kind}.count"]) == pytest.approx(len(rows), abs=1e-3)
        np.testing.assert_allclose(actor[f"encoder.normalizer.stats.{kind}.mean"].numpy(), rows[:, :47].mean(0),
                                   rtol=1e-3, atol=1e-3)
    row = rows_of(tmp_path / "fleet" / "metrics.jsonl")[-1]
    assert "eval/sim_sawyer/success_rate" in row and "eval/sim_so101/success_rate" in row
    assert "eval/sim_so101/return_mean" in row and "eval/sim_sawyer/return_mean" in row


@pytest.mark.slow  # two real-time simulated arms, both rendering
def test_two_embodiments_with_different_cameras_feed_one_pixel_policy(ray_cluster, tmp_path):
    """The Sawyer's 40x48 corner camera and the SO-101's 32x32 front camera, both named "main" and
    resized to 24x24 at their robots: one conv encoder and one store field serve both."""
    fleet = [{"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 20.0, "image_size": [40, 48]}},
             {"kind": "sim_so101", "options": {"control_hz": 20.0, "image_size": 32},
              "task": {"observations": ["proprio", "block_position"], "rewards": {"block_distance": 1.0},
                       "cameras": ["front"], "camera_names": {"front": "main"}}}]
    summary = run(make_cfg(tmp_path / "fleet", 1, robot={"fleet": fleet},
                           task={"observations": ["proprio", "sim_state"], "max_episode_steps": 10,
                                 "cameras": ["corner"], "camera_names": {"corner": "main"}, "frame_size": [24, 24]},
                           network={**PIXELS["network"]}, placement={"robot": "0-1"}, eval={"every": 0, "episodes": 1}))
    assert summary["replay_episodes"] >= 2
    store = ReplayStore(str(tmp_path / "fleet" / "replay"), writable=False)
    try:
        episodes = [store.episode(i) for i in range(store.num_episodes)]
    finally:
        store.close()
    kinds = {int(np.argmax(e["state"][0, -2:])) for e in episodes}
    assert kinds == {0, 1} and all(e["pixels.main"].shape[1:] == (24, 24, 3) for e in episodes)


def test_fleet_size_must_match_the_robot_ranks(ray_cluster, tmp_path):
    with pytest.raises(ConfigError, match="robot.fleet has 1 entries"):
        run(make_cfg(tmp_path / "bad_fleet", 1, robot={"fleet": [{"kind": "sim_sawyer", "options": {
            "image_size": None}}]}, placement={"robot": "0-1"}))


# A 40x48 camera resized at the robot to the 32x32 training frames (task.frame_size).
PIXELS = {"robot": {"kind": "sim_sawyer", "options": {"task": "reach-v3", "control_hz": 50.0, "image_size": [40, 48]}},
          "task": {"max_episode_steps": 20, "cameras": ["corner"], "frame_size": [32, 32]},
          "network": {"actor_hidden": [32, 32], "critic_hidden": [32, 32], "encoder": "cnn",
                      "cnn": {"channels": [8, 8], "strides": [2, 2], "feature_dim": 16, "augment_pad": 2}}}
FLOW = {"network": {"actor_hidden": [32, 32], "critic_hidden": [32, 32], "actor": "flow",
                    "flow": {"num_steps": 2, "hidden": [32, 32]}}}


# Slow tier (default-tier budget): two runs each; the pixel learner, its actor and its resume are
# also checked without Ray in tests/unit/realworld/test_pipeline_parts.py.
@pytest.mark.slow
@pytest.mark.parametrize("extra", [PIXELS, FLOW], ids=["cnn_from_pixels", "sac_flow"])
def test_pixel_and_flow_networks_train_checkpoint_and_resume(ray_cluster, tmp_path, extra):
    """network.encoder=cnn (the robot acts from its camera frames, the learner samples them from the
    store, the published weights carry the encoder) and network.actor=flow: both run, checkpoint,
    and a second run of the same folder resumes from the checkpoint and goes on updating."""
    import torch

    first = run(make_cfg(tmp_path / "run", 1, **extra))
    assert first["updates"] > 0 and first["version"] >= 1
    checkpoint = torch.load(next((tmp_path / "run" / "checkpoints").glob("iter_*")) / "learner" / "learner.pt",
                            map_location="cpu", weights_only=False)
    actor = checkpoint["agent"]["actor"]
    if extra is PIXELS:
        assert any(name.startswith("encoder.trunks.corner") for name in actor)
        assert "augment_generator" in checkpoint["agent"]
        store = ReplayStore(str(tmp_path / "run" / "replay"), writable=False)
        try:
            assert store.episode(0)["pixels.corner"].shape[1:] == (32, 32, 3)
        finally:
            store.close()
    else:
        assert any(name.startswith("flow.") for name in actor)
    resumed = run(make_cfg(tmp_path / "run", 2, **extra))
    assert resumed["updates"] > first["updates"] and resumed["replay_episodes"] > first["replay_episodes"]
    assert [r["step"] for r in rows_of(tmp_path / "run" / "metrics.jsonl")] == [1, 2]
