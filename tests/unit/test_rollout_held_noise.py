"""The rollout seeds a policy's held exploration noise (``Policy.held_noise_every``): one seed per
stage and window of decisions, the same whatever order stages are served in, new each window,
each stage and each iteration; a policy holding none is never asked."""

from __future__ import annotations

import pytest

pytest.importorskip("gymnasium")

from tests.unit.test_rollout_last_step import ENVS, EPISODE, rollout_with_local_env  # noqa: E402


def recording(worker, every: int) -> list[int]:
    seeds: list[int] = []
    worker.policy.policy.held_noise_every = every
    worker.policy.policy.hold_noise = seeds.append
    return seeds


@pytest.mark.parametrize("stages", [1, 2])
def test_each_stage_holds_one_seed_per_window_of_decisions(stages):
    worker = rollout_with_local_env(stages)
    try:
        seeds = recording(worker, every=2)
        worker.collect(0, list(range(ENVS)), num_steps=2 * EPISODE)  # 6 decisions a stage: windows 0 0 1 1 2 2
        by_stage = [seeds[stage::stages] for stage in range(stages)]  # served in turn: stage 0, 1, 0, 1, ...
        for decisions in by_stage:
            assert len(decisions) == 2 * EPISODE
            assert decisions[0] == decisions[1] and decisions[2] == decisions[3] and decisions[4] == decisions[5]
            assert len({decisions[0], decisions[2], decisions[4]}) == 3
        if stages == 2:
            assert not set(by_stage[0]) & set(by_stage[1])
        again = recording(worker, every=2)
        worker.collect(0, list(range(ENVS)), num_steps=2 * EPISODE)
        assert again == seeds  # the same iteration: the same seeds
        later = recording(worker, every=2)
        worker.collect(1, list(range(ENVS)), num_steps=2 * EPISODE)
        assert not set(later) & set(seeds)
    finally:
        worker.close()


def test_a_policy_that_holds_no_noise_is_not_asked():
    worker = rollout_with_local_env(1)
    try:
        seeds = recording(worker, every=0)
        worker.collect(0, list(range(ENVS)), num_steps=EPISODE)
        assert seeds == []
    finally:
        worker.close()
