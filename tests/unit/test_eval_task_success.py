"""Per-task held-out success of multi-task envs (``eval/success/<task>``): the env says which task
each sub-env runs, the evaluation groups episodes by it, and parts evaluated on several rollout
ranks merge weighted by their episodes of each task."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch
from torch import nn

from infinirl.components.embodied_rollout import merge_task_success, run_eval_episodes
from infinirl.envs.chunking import ActionChunkEnv
from infinirl.envs.vector import VectorEnv
from infinirl.models.policies.base import PolicyStep
from tests.unit.envs.toy_envs import CounterEnv


@dataclass(frozen=True)
class TwoTaskFactory:
    """Env ``i`` runs ``easy`` (success at step 2 of 5) for even ``i``, ``never`` otherwise."""

    def __call__(self, index: int) -> CounterEnv:
        return CounterEnv(episode_length=5, success_at=2 if index % 2 == 0 else 99)

    def task_names(self, num_envs: int) -> list[str]:
        return ["easy" if index % 2 == 0 else "never" for index in range(num_envs)]


@dataclass(frozen=True)
class OneTaskFactory:
    def __call__(self, index: int) -> CounterEnv:
        return CounterEnv(episode_length=5, success_at=2 if index % 2 == 0 else 99)


class ZeroPolicy(nn.Module):
    chunk = 1

    def act(self, obs, deterministic: bool = True) -> PolicyStep:
        batch = len(obs["state"])
        return PolicyStep(actions=torch.zeros(batch, 1, 2), logprobs=torch.zeros(batch, 1))


class NoisyPolicy(nn.Module):
    """Acts with fresh noise even when deterministic (as a flow policy's initial noise): success
    depends on the draws."""

    chunk = 1

    def act(self, obs, deterministic: bool = True) -> PolicyStep:
        batch = len(obs["state"])
        return PolicyStep(actions=torch.rand(batch, 1, 2) * 2 - 1, logprobs=torch.zeros(batch, 1))


def test_eval_noise_is_seeded_by_the_episodes_and_leaves_the_global_stream_alone():
    env = VectorEnv(OneTaskFactory(), 2, num_workers=0)
    try:
        results = []
        for global_seed in (1, 2):
            torch.manual_seed(global_seed)
            results.append(run_eval_episodes(NoisyPolicy(), env, seeds=list(range(8))))
            after = torch.rand(1)
            torch.manual_seed(global_seed)
            assert torch.equal(after, torch.rand(1))  # the caller's stream is where it was
    finally:
        env.close()
    assert results[0] == results[1]


def test_vector_env_and_chunk_wrapper_report_each_envs_task():
    env = VectorEnv(TwoTaskFactory(), 3, num_workers=0)
    try:
        assert env.task_names == ["easy", "never", "easy"]
        assert ActionChunkEnv(env, 2).task_names == ["easy", "never", "easy"]
    finally:
        env.close()
    plain = VectorEnv(OneTaskFactory(), 2, num_workers=0)
    try:
        assert plain.task_names is None
    finally:
        plain.close()


def test_eval_reports_success_per_task():
    env = VectorEnv(TwoTaskFactory(), 4, num_workers=0)
    try:
        # 6 seeds in rounds of 4: envs 0-3, then envs 0-1 -> easy 2+1, never 2+1 episodes
        result = run_eval_episodes(ZeroPolicy(), env, seeds=list(range(6)))
    finally:
        env.close()
    assert result["eval/success_rate"] == pytest.approx(0.5)
    assert result["eval/success/easy"] == 1.0 and result["eval/success/never"] == 0.0
    assert result["eval/episodes/easy"] == 3 and result["eval/episodes/never"] == 3


def test_single_task_env_has_no_per_task_keys():
    env = VectorEnv(OneTaskFactory(), 2, num_workers=0)
    try:
        result = run_eval_episodes(ZeroPolicy(), env, seeds=[0, 1])
    finally:
        env.close()
    assert not [key for key in result if key.startswith(("eval/success/", "eval/episodes/"))]


def test_merge_weights_each_part_by_its_episodes_of_the_task():
    parts = [{"eval/success/a": 1.0, "eval/episodes/a": 3, "eval/success/b": 0.5, "eval/episodes/b": 2},
             {"eval/success/a": 0.0, "eval/episodes/a": 1}]
    merged = merge_task_success(parts)
    assert merged["eval/success/a"] == pytest.approx(0.75) and merged["eval/episodes/a"] == 4
    assert merged["eval/success/b"] == pytest.approx(0.5) and merged["eval/episodes/b"] == 2
    assert merge_task_success([{"eval/success_rate": 1.0, "eval/episodes": 2}]) == {}


def test_metaworld_task_list_names_each_env():
    from infinirl.envs.metaworld_env import metaworld_factory

    factory = metaworld_factory("reach-v3,push-v3")
    assert factory.task_names(3) == ["reach-v3", "push-v3", "reach-v3"]
    assert np.unique(metaworld_factory("MT10").task_names(10)).size == 10


def test_libero_suite_names_each_env_by_suite_and_task_index():
    from infinirl.envs.libero_env import LiberoFactory

    factory = LiberoFactory("libero_goal", (0, 3, 7))
    assert factory.task_names(4) == ["libero_goal/0", "libero_goal/3", "libero_goal/7", "libero_goal/0"]
