"""Which worker processes spin in OpenMP before sleeping (``spin_wait_env``): every rank that
computes with several torch threads, so that the helper thread of its many short parallel regions
(a PPO update, a VLA's denoising steps) is not put to sleep and woken between each pair of them
under the workers' ``OMP_WAIT_POLICY=PASSIVE``; a one-thread rank has no helper to keep awake."""

import pytest

from infinirl.config import to_dataclass
from infinirl.utils.threads import spin_wait_env


@pytest.mark.parametrize("num_threads, spins", [(1, False), (2, True), (0, True)])  # 0: every core
def test_spin_wait_env_for_several_threads_only(num_threads, spins):
    env = spin_wait_env(num_threads)
    assert (env == {"GOMP_SPINCOUNT": "300000"}) is spins
    assert spins or env == {}


def test_embodied_rollout_and_actor_ranks_spin_by_their_own_threads():
    pytest.importorskip("metaworld")
    from infinirl.runners.embodied import worker_process_env
    from infinirl.runners.embodied_config import EmbodiedConfig

    cfg = to_dataclass(EmbodiedConfig, {"env": {"name": "metaworld:reach-v3", "num_envs": 2}, "rollout_steps": 8,
                                        "rollout": {"num_threads": 2}, "actor": {"num_threads": 1},
                                        "algorithm": {"mini_batches": 2}, "eval": {"video_episodes": 0}})
    env = worker_process_env(cfg)
    assert env["rollout"] == {"GOMP_SPINCOUNT": "300000"}  # the VLA demos act with two threads
    assert env["actor"] == {}


def test_reasoning_ranks_spin_by_their_own_threads():
    from infinirl.runners.reasoning import worker_process_env
    from infinirl.runners.reasoning_config import ReasoningConfig

    spins = {"GOMP_SPINCOUNT": "300000"}
    default = worker_process_env(to_dataclass(ReasoningConfig, {}))  # num_threads 0: every core
    assert default["actor"] == default["rollout"] == default["reference"] == spins
    assert default["reward"] == {}  # verifiers run no parallel torch
    one = worker_process_env(to_dataclass(ReasoningConfig, {"num_threads": 1, "rollout": {"num_threads": 2}}))
    assert one["actor"] == one["critic"] == {} and one["rollout"] == spins
