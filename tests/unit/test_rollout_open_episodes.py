"""The rollout's trajectory carries the episodes still running when the collection ends.

An episode longer than an iteration never finishes within one (every iteration resets every env),
so ``trajectory["episodes"]`` stays empty; ``trajectory["open_episodes"]`` then says how far each
env's episode got: return so far and steps so far, per env, in the trajectory's env order.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gymnasium")

from infinirl.components.embodied_rollout import EmbodiedRolloutWorker, PolicySpec  # noqa: E402
from infinirl.components.env_worker import EnvSpec, probe_env_specs  # noqa: E402
from infinirl.runtime.worker import RankContext  # noqa: E402

ENVS, EPISODE = 4, 3


def rollout(stages: int, chunk: int = 1, episode: int | None = EPISODE) -> EmbodiedRolloutWorker:
    spec = EnvSpec(name="gym:Pendulum-v1", num_envs=ENVS, stages=stages, num_workers=0, max_episode_steps=episode,
                   chunk_size=chunk)
    observation_spec, action_space = probe_env_specs(spec.name, {})
    worker = EmbodiedRolloutWorker.__new__(EmbodiedRolloutWorker)
    worker.ctx = RankContext("rollout", 0, 1)
    worker.__init__(spec, PolicySpec(name="mlp_gaussian", options={"hidden": [8]}, chunk=chunk), observation_spec,
                    action_space, seed=0, host_env=True)
    return worker


def reference(trajectory: dict) -> tuple[np.ndarray, np.ndarray]:
    """Slow float64 reference: per env, the rewards and steps after its last episode end."""
    step_rewards, step_mask = trajectory["step_rewards"], trajectory["step_mask"]  # [T, n, K]
    done = trajectory["terminated"] | trajectory["truncated"]
    steps, envs, actions = step_rewards.shape
    returns, lengths = np.zeros(envs, np.float64), np.zeros(envs, np.int64)
    for i in range(envs):
        ended = np.flatnonzero(done[:, i])
        start = ended[-1] + 1 if len(ended) else 0
        total, length = 0.0, 0
        for t in range(start, steps):
            for k in range(actions):
                if step_mask[t, i, k]:
                    total += float(step_rewards[t, i, k])
                    length += 1
        returns[i], lengths[i] = total, length
    return returns, lengths


@pytest.mark.parametrize("stages,chunk", [(1, 1), (2, 1), (2, 2)])
def test_open_episodes_are_the_rewards_and_steps_since_the_last_episode_end(stages, chunk):
    worker = rollout(stages, chunk)
    try:
        trajectory = worker.collect(0, list(range(ENVS)), num_steps=7)
        open_episodes = trajectory["open_episodes"]
        assert set(open_episodes) == {"return", "length"}
        assert open_episodes["return"].shape == open_episodes["length"].shape == (ENVS,)
        assert open_episodes["return"].dtype == np.float64 and open_episodes["length"].dtype == np.int64
        returns, lengths = reference(trajectory)
        np.testing.assert_array_equal(open_episodes["length"], lengths)
        np.testing.assert_allclose(open_episodes["return"], returns, rtol=1e-12)
        assert (lengths > 0).all() and (lengths < EPISODE).all()
        # the env's own statistics of its running episodes agree exactly
        own = [env.open_episodes() for env in worker.env.envs]
        for key in ("return", "length"):
            np.testing.assert_array_equal(open_episodes[key], np.concatenate([o[key] for o in own]))
    finally:
        worker.close()


def test_an_episode_longer_than_the_collection_is_reported_open():
    worker = rollout(2, episode=None)  # Pendulum's own limit: 200 steps
    try:
        trajectory = worker.collect(0, list(range(ENVS)), num_steps=5)
        assert len(trajectory["episodes"]["return"]) == 0
        np.testing.assert_array_equal(trajectory["open_episodes"]["length"], [5] * ENVS)
        expected = trajectory["rewards"].astype(np.float64).sum(axis=0)
        np.testing.assert_allclose(trajectory["open_episodes"]["return"], expected, rtol=1e-12)
        assert (trajectory["open_episodes"]["return"] < 0).all()  # Pendulum's rewards are costs
    finally:
        worker.close()


def test_an_episode_that_ended_on_the_last_step_is_not_open():
    worker = rollout(1)
    try:
        trajectory = worker.collect(0, list(range(ENVS)), num_steps=2 * EPISODE)
        assert len(trajectory["episodes"]["return"]) == 2 * ENVS
        np.testing.assert_array_equal(trajectory["open_episodes"]["length"], [0] * ENVS)
        np.testing.assert_array_equal(trajectory["open_episodes"]["return"], [0.0] * ENVS)
    finally:
        worker.close()
