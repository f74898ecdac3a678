"""The rollout's last step of an iteration resets no env, in process and across the link.

Every iteration starts by resetting every env with its own seed, so an episode that ends on the
iteration's last step would otherwise be reset once more for an observation nobody reads (its
bootstrap value is masked: ``test_bootstrap_of_an_env_that_ended_on_the_last_step_is_unused``).
A simulator reset can cost as much as many steps (MetaWorld rebuilds its scene layout).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gymnasium")

from infinirl.components.embodied_rollout import EmbodiedRolloutWorker, PolicySpec  # noqa: E402
from infinirl.components.env_worker import EnvSpec, probe_env_specs  # noqa: E402
from infinirl.envs.gymnasium_env import GymnasiumSubEnv  # noqa: E402
from infinirl.runtime.worker import RankContext  # noqa: E402

ENVS, EPISODE = 4, 3


@pytest.fixture
def reset_count(monkeypatch):
    """Counts sub-env resets in this process (the sub-envs run here: num_workers=0)."""
    calls = []
    original = GymnasiumSubEnv.reset

    def counting(self, *args, **kwargs):
        calls.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(GymnasiumSubEnv, "reset", counting)
    return calls


def rollout_with_local_env(stages: int) -> EmbodiedRolloutWorker:
    spec = EnvSpec(name="gym:Pendulum-v1", num_envs=ENVS, stages=stages, num_workers=0, max_episode_steps=EPISODE)
    observation_spec, action_space = probe_env_specs(spec.name, {})
    worker = EmbodiedRolloutWorker.__new__(EmbodiedRolloutWorker)
    worker.ctx = RankContext("rollout", 0, 1)
    worker.__init__(spec, PolicySpec(name="mlp_gaussian", options={"hidden": [8]}), observation_spec, action_space,
                    seed=0, host_env=True)
    return worker


@pytest.mark.parametrize("stages", [1, 2])
def test_collect_resets_each_env_once_per_episode_not_after_the_last_step(reset_count, stages):
    worker = rollout_with_local_env(stages)
    try:
        reset_count.clear()
        trajectory = worker.collect(0, list(range(ENVS)), num_steps=2 * EPISODE)
        # per env: the iteration's seeded reset and the auto-reset after the first episode; the
        # second episode ends on the last step and is not reset
        assert len(reset_count) == 2 * ENVS
        assert trajectory["truncated"][EPISODE - 1].all() and trajectory["truncated"][-1].all()
        assert len(trajectory["episodes"]["return"]) == 2 * ENVS
        assert np.isfinite(trajectory["bootstrap_values"]).all()
        reset_count.clear()
        again = worker.collect(1, list(range(10, 10 + ENVS)), num_steps=2 * EPISODE)  # the next iteration starts
        assert len(reset_count) == 2 * ENVS
        assert not np.array_equal(again["obs"]["state"][0], trajectory["obs"]["state"][0])  # its own seeds
    finally:
        worker.close()
