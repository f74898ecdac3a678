"""The SAC collector in-process (no Ray): transitions, episodes spanning calls, and exact resume by
replaying each env's current episode (also right after an episode ended: empty history)."""

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")

from infinirl.components.sac_collector import CollectorEnvSpec, SACCollectorWorker  # noqa: E402
from infinirl.components.sac_learner import SACNetSpec  # noqa: E402
from infinirl.envs.base import ActionSpace  # noqa: E402
from infinirl.runtime import RankContext  # noqa: E402

SPACE = ActionSpace.box([-2.0], [2.0])
NET = SACNetSpec(actor_hidden=(16,), critic_hidden=(16,))


def make_collector(seed=0, num_envs=2, num_workers=0):
    worker = SACCollectorWorker.__new__(SACCollectorWorker)
    worker.ctx = RankContext("collector", 0, 1)  # what the runtime sets before __init__
    env = CollectorEnvSpec(name="gym:Pendulum-v1", num_envs=num_envs, num_workers=num_workers, seed=seed)
    worker.__init__(env, NET, 3, SPACE, seed, num_threads=1)
    torch.manual_seed(1)
    weights = NET.build_actor(3, SPACE).state_dict()
    worker.load_weights(weights.items(), version=0)
    return worker


def same(a: dict, b: dict) -> None:
    for key in ("obs", "action", "reward", "next_obs", "terminated", "env_step", "logprob"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_collects_transitions_and_resumes_exactly(tmp_path):
    collector = make_collector()
    first = collector.collect(30, random_steps=10)
    assert first["obs"].shape == (60, 3) and first["action"].shape == (60, 1)
    assert np.abs(first["action"]).max() <= 1.0  # the [-1, 1] action is stored, not the env's
    assert not first["policy_mask"][:20].any() and first["policy_mask"][20:].all()
    np.testing.assert_array_equal(first["next_obs"][:-2], first["obs"][2:])  # rows are (t, env), time-major
    assert first["env_step"].tolist() == [2 * (i // 2) for i in range(60)]
    collector.save_state(str(tmp_path / "ckpt"))

    resumed = make_collector(seed=123)  # every generator and env state comes from the file
    report = resumed.load_state(str(tmp_path / "ckpt"))
    assert report == {"replayed_steps": 60, "mismatched_envs": []}
    for _ in range(2):
        same(collector.collect(25), resumed.collect(25))

    # Pendulum episodes end at 200 steps: land exactly on an episode end, then save (empty history).
    collector.collect(200 - 80)
    assert collector.history == [[], []]
    collector.save_state(str(tmp_path / "boundary"))
    again = make_collector(seed=7)
    assert again.load_state(str(tmp_path / "boundary"))["replayed_steps"] == 0
    a, b = collector.collect(10), again.collect(10)
    same(a, b)
    assert collector.episodes == again.episodes == 2


def test_eval_is_deterministic_and_held_out():
    collector = make_collector()
    seeds = [2**31 + i for i in range(3)]
    first = collector.evaluate(seeds, num_envs=2)
    assert first["eval/episodes"] == 3 and first["eval/length_mean"] == 200
    assert collector.evaluate(seeds, num_envs=2) == first


def test_envs_in_subprocesses_collect_the_same_data():
    local, spawned = make_collector(), make_collector(num_workers=1)  # each env in its own process
    try:
        assert len({p.pid for env in spawned.envs for p in env.worker_processes}) == 2
        for steps, random_steps in ((15, 5), (10, 0)):
            same(local.collect(steps, random_steps), spawned.collect(steps, random_steps))
    finally:
        local.close()
        spawned.close()


def test_open_episodes_span_collections_and_resume_exactly(tmp_path):
    """Pendulum's 200-step episodes outlast a collection of 30 steps: no episode ends, and
    ``open_episodes`` carries each env's return and steps so far, across calls and a resume."""
    collector = make_collector()
    rewards = []
    for steps in (30, 20):
        batch = collector.collect(steps, random_steps=10)
        assert len(batch["episodes"]["return"]) == 0
        rewards.append(batch["reward"].reshape(steps, 2))
        open_episodes = batch["open_episodes"]
        assert open_episodes["return"].dtype == np.float64 and open_episodes["length"].dtype == np.int64
    np.testing.assert_array_equal(open_episodes["length"], [50, 50])
    expected = [sum(float(r) for r in env_rewards) for env_rewards in np.concatenate(rewards).T]  # float64, in order
    np.testing.assert_allclose(open_episodes["return"], expected, rtol=1e-12)

    collector.save_state(str(tmp_path / "ckpt"))
    resumed = make_collector(seed=5)
    resumed.load_state(str(tmp_path / "ckpt"))
    np.testing.assert_array_equal(resumed.open_episodes()["return"], open_episodes["return"])
    a, b = collector.collect(150), resumed.collect(150)  # lands on the episodes' end
    assert len(a["episodes"]["return"]) == 2
    for key in ("return", "length"):
        np.testing.assert_array_equal(a["open_episodes"][key], b["open_episodes"][key])
        np.testing.assert_array_equal(a["open_episodes"][key], [0, 0])
