"""The vectoriser: auto-reset, seeding, fixed states, masks, crash recovery, clean shutdown.

Uses the toy ``CounterEnv`` (state = [episode seed, step t, action sum]) so every expectation is
exact. Process-based tests use 2 workers; in-process (``num_workers=0``) shares the same code.
"""

import os

import numpy as np
import pytest

from infinirl.envs import EnvCrashError, VectorEnv
from tests.unit.envs.toy_envs import BrokenFactory, CounterFactory

ONES = np.ones((4, 2), dtype=np.float32)


def _steps(env, count, actions=ONES):
    return [env.step(actions[: env.num_envs]) for _ in range(count)]


def test_auto_reset_returns_next_first_obs_and_keeps_final_obs():
    with VectorEnv(CounterFactory(episode_length=3, success_at=3), 2, num_workers=0) as env:
        first = env.reset(seeds=[10, 20])
        np.testing.assert_array_equal(first["state"][:, :2], [[10, 0], [20, 0]])
        results = _steps(env, 3)
        assert not results[0].done.any() and not results[1].done.any()
        last = results[-1]
        assert last.terminated.all() and not last.truncated.any()
        np.testing.assert_array_equal(last.obs["state"][:, 1], [0, 0])  # a new episode began
        assert not np.isin(last.obs["state"][:, 0], [10, 20]).any()  # ... with a fresh seed
        final = last.info["final_obs"]["state"]
        np.testing.assert_array_equal(final, [[10, 3, 6], [20, 3, 6]])
        assert last.info["final_obs"]["instruction"] == ["count 10", "count 20"]
        assert last.info["final_obs_mask"].all()
        np.testing.assert_array_equal(last.info["episode_return"], [3, 3])
        np.testing.assert_array_equal(last.info["episode_length"], [3, 3])
        assert last.info["episode_success"].all() and last.info["success"].all()
        assert not results[0].info["final_obs_mask"].any()
        assert not results[0].info["success"].any()


@pytest.mark.parametrize("num_workers", [0, 2])
def test_step_without_autoreset_leaves_ended_envs_ended_until_reset(num_workers):
    """``autoreset=False`` (a rollout's last step, whose next observation nobody uses): an env
    whose episode ends is not reset; its row keeps the final observation, and stepping it again
    before ``reset`` is refused, while masking it out lets the others go on."""
    with VectorEnv(CounterFactory(episode_length=3, success_at=3), 2, num_workers=num_workers) as env:
        env.reset(seeds=[10, 20])
        env.step(ONES[:2], env_mask=np.array([True, False]))  # env 0 is one step ahead
        env.step(ONES[:2])
        last = env.step(ONES[:2], autoreset=False)  # env 0 ends (t = 3), env 1 does not (t = 2)
        np.testing.assert_array_equal(last.done, [True, False])
        np.testing.assert_array_equal(last.obs["state"], [[10, 3, 6], [20, 2, 4]])  # no new episode
        np.testing.assert_array_equal(last.info["final_obs"]["state"][0], [10, 3, 6])
        np.testing.assert_array_equal(last.info["episode_return"], [3, 0])
        np.testing.assert_array_equal(last.info["episode_length"], [3, 0])
        with pytest.raises(RuntimeError, match=r"env\(s\) \[0\] ended .*autoreset=False.*reset\(\)"):
            env.step(ONES[:2])
        waited = env.step(ONES[:2], env_mask=np.array([False, True]))  # env 1 ends and auto-resets
        np.testing.assert_array_equal(waited.obs["state"][:, 1], [3, 0])
        np.testing.assert_array_equal(waited.reward, [0, 1])
        first = env.reset(seeds=[1, 2])
        np.testing.assert_array_equal(first["state"][:, :2], [[1, 0], [2, 0]])
        np.testing.assert_array_equal(env.step(ONES[:2]).obs["state"][:, 1], [1, 1])  # steppable again


def test_same_seed_gives_same_episodes_and_int_seed_counts_up():
    def episode_seeds(env):
        env.reset()
        seeds = [env.step(ONES[:3]).obs["state"][:, 0] for _ in range(4)]
        return np.stack(seeds)

    with VectorEnv(CounterFactory(episode_length=1), 3, num_workers=0, seed=5) as a:
        with VectorEnv(CounterFactory(episode_length=1), 3, num_workers=0, seed=5) as b:
            np.testing.assert_array_equal(episode_seeds(a), episode_seeds(b))
        np.testing.assert_array_equal(a.reset(seeds=7)["state"][:, 0], [7, 8, 9])


def test_state_ids_start_groups_identically_and_keep_them_in_lockstep():
    with VectorEnv(CounterFactory(episode_length=2), 4, num_workers=0) as env:
        obs = env.reset(state_ids=[3, 3, 9, 9])
        np.testing.assert_array_equal(obs["state"][:, 0], [3, 3, 9, 9])
        for _ in range(4):  # two auto-resets: the groups get new, but shared, episodes
            seeds = env.step(ONES).obs["state"][:, 0]
            assert seeds[0] == seeds[1] and seeds[2] == seeds[3] and seeds[0] != seeds[2]
        with pytest.raises(ValueError, match="seeds or state_ids"):
            env.reset(seeds=[1, 2, 3, 4], state_ids=[0, 0, 0, 0])
        with pytest.raises(ValueError, match="expected 4 state_ids"):
            env.reset(state_ids=[0, 0])


def test_env_mask_leaves_masked_envs_untouched():
    with VectorEnv(CounterFactory(episode_length=10), 2, num_workers=0) as env:
        env.reset(seeds=0)
        result = env.step(ONES[:2], env_mask=np.array([True, False]))
        np.testing.assert_array_equal(result.obs["state"][:, 1], [1, 0])
        np.testing.assert_array_equal(result.reward, [1, 0])
        result = env.step(ONES[:2])
        np.testing.assert_array_equal(result.obs["state"][:, 1], [2, 1])


def test_max_episode_steps_truncates_without_terminating():
    with VectorEnv(CounterFactory(episode_length=100), 2, num_workers=0, max_episode_steps=4) as env:
        env.reset(seeds=0)
        results = _steps(env, 4)
        assert not any(r.done.any() for r in results[:3])
        assert results[-1].truncated.all() and not results[-1].terminated.any()
        np.testing.assert_array_equal(results[-1].info["episode_length"], [4, 4])


def test_wrong_usage_fails_with_clear_messages():
    with VectorEnv(CounterFactory(), 2, num_workers=0) as env:
        with pytest.raises(RuntimeError, match="reset"):
            env.step(ONES[:2])
        env.reset()
        with pytest.raises(ValueError, match=r"expected actions of shape \(2, 2\)"):
            env.step(np.ones((2, 3)))


def test_worker_processes_give_the_same_results_as_in_process():
    """3 envs over 2 workers (uneven blocks) must match stepping them in this process."""
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (3, 2)).astype(np.float32) for _ in range(7)]
    outputs = []
    for num_workers in (0, 2):
        with VectorEnv(CounterFactory(episode_length=3), 3, num_workers=num_workers, seed=1) as env:
            env.reset()
            results = [env.step(a) for a in actions]
            outputs.append([(r.obs["state"], r.reward, r.terminated) for r in results])
            assert len(env.worker_processes) == num_workers
            np.testing.assert_array_equal(env.render()[:, 0, 0, 0], results[-1].obs["state"][:, 1])
    for (obs_a, rew_a, term_a), (obs_b, rew_b, term_b) in zip(*outputs, strict=True):
        np.testing.assert_array_equal(obs_a, obs_b)
        np.testing.assert_array_equal(rew_a, rew_b)
        np.testing.assert_array_equal(term_a, term_b)


def test_sub_env_that_raises_is_rebuilt_and_its_episode_truncated():
    factory = CounterFactory(episode_length=100, crash_index=1, crash_at=3, crash_mode="raise")
    with VectorEnv(factory, 4, num_workers=2) as env:
        env.reset(seeds=0)
        pids = [p.pid for p in env.worker_processes]
        before, crashed, after = _steps(env, 2)[1], env.step(ONES), env.step(ONES)
        np.testing.assert_array_equal(crashed.info["restarted"], [False, True, False, False])
        np.testing.assert_array_equal(crashed.truncated, [False, True, False, False])
        assert "crashed on purpose" in crashed.info["restart_errors"][1]
        # its last good observation is kept as the final one; the new episode starts at t = 0
        np.testing.assert_array_equal(crashed.info["final_obs"]["state"][1], before.obs["state"][1])
        assert crashed.obs["state"][1, 1] == 0 and crashed.obs["state"][0, 1] == 3
        assert not after.info["restarted"].any() and after.obs["state"][1, 1] == 1
        assert [p.pid for p in env.worker_processes] == pids  # recovered inside its worker
        assert env.restart_count == 1


def test_worker_process_that_dies_is_replaced_and_training_continues():
    factory = CounterFactory(episode_length=100, crash_index=1, crash_at=2, crash_mode="exit")
    with VectorEnv(factory, 4, num_workers=2) as env:
        env.reset(seeds=0)
        old_pid = env.worker_processes[0].pid
        first = env.step(ONES)
        crashed = env.step(ONES)
        # envs 0 and 1 shared the dead process: both lost their episodes
        np.testing.assert_array_equal(crashed.info["restarted"], [True, True, False, False])
        np.testing.assert_array_equal(crashed.truncated, [True, True, False, False])
        assert "died" in crashed.info["restart_errors"][0]
        np.testing.assert_array_equal(crashed.info["final_obs"]["state"][:2], first.obs["state"][:2])
        np.testing.assert_array_equal(crashed.obs["state"][:, 1], [0, 0, 2, 2])
        assert env.worker_processes[0].pid != old_pid
        assert env.step(ONES).obs["state"][0, 1] == 1


def test_hanging_worker_is_killed_after_the_step_timeout():
    factory = CounterFactory(episode_length=100, crash_index=3, crash_at=2, crash_mode="hang")
    with VectorEnv(factory, 4, num_workers=2, step_timeout_s=1.0) as env:
        env.reset(seeds=0)
        env.step(ONES)
        hung = env.step(ONES)
        np.testing.assert_array_equal(hung.info["restarted"], [False, False, True, True])
        assert "no answer within 1.0 s" in hung.info["restart_errors"][3]


def test_unbuildable_sub_env_reports_the_root_cause():
    with pytest.raises(EnvCrashError, match="simulator assets missing"):
        VectorEnv(BrokenFactory(), 2, num_workers=1)


def test_more_crashes_than_max_restarts_stop_the_run():
    factory = CounterFactory(crash_index=0, crash_at=1, crash_mode="raise")  # crashes every step
    with VectorEnv(factory, 2, num_workers=0, max_restarts=2) as env:
        env.reset()
        _steps(env, 2)
        with pytest.raises(EnvCrashError, match="(?s)exceed max_restarts=2.*crashed on purpose"):
            env.step(ONES[:2])


def test_close_reaps_every_worker_process():
    env = VectorEnv(CounterFactory(), 4, num_workers=2)
    env.reset()
    processes = env.worker_processes
    assert all(p.is_alive() for p in processes)
    env.close()
    env.close()  # idempotent
    for process in processes:
        assert process.exitcode == 0  # exited cleanly and was joined
        assert not os.path.exists(f"/proc/{process.pid}")  # reaped: no zombie left
