"""Embodied GRPO in the embodied runner, without Ray: seed groups (and that a group really starts
from one state, across rank and pipeline-stage boundaries), the advantage batch with its episode
mask, and the actor update ignoring masked decisions and training no critic."""

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")

from infinirl.components.embodied_actor import ppo_update  # noqa: E402
from infinirl.components.embodied_rollout import PolicySpec  # noqa: E402
from infinirl.components.env_worker import EnvSpec, StagedEnv, iteration_seeds, probe_env_specs  # noqa: E402
from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.runners.embodied import EmbodiedFlow, ppo_spec  # noqa: E402
from infinirl.runners.embodied_config import EmbodiedConfig  # noqa: E402


def grpo_cfg(**extra):
    raw = {"iterations": 2, "rollout_steps": 5, "env": {"name": "gym:Pendulum-v1", "num_envs": 4},
           "algorithm": {"name": "grpo", "group_size": 2, "epochs": 2, "mini_batches": 2}, **extra}
    return to_dataclass(EmbodiedConfig, raw)


def test_iteration_seeds_come_in_groups_and_ppo_seeds_are_unchanged():
    seeds = iteration_seeds(3, 7, 12, group_size=4)
    groups = [seeds[i:i + 4] for i in range(0, 12, 4)]
    assert all(len(set(g)) == 1 for g in groups)  # consecutive envs share one seed
    assert len({g[0] for g in groups}) == 3  # distinct across groups
    assert seeds == iteration_seeds(3, 7, 12, group_size=4)  # a function of (seed, iteration)
    assert iteration_seeds(3, 8, 12, group_size=4) != seeds
    rng = np.random.default_rng([3, 7, 0x5EED])  # group_size 1 (PPO): the seeds it always had
    assert iteration_seeds(3, 7, 12) == [int(s) for s in rng.integers(0, 2**31 - 1, size=12)]
    with pytest.raises(ValueError, match="group_size=5"):
        iteration_seeds(0, 0, 12, group_size=5)


def _grouped_first_obs(name: str, kwargs: dict, num_envs: int, ranks: int, stages: int, group_size: int):
    """Reset the envs of every rank (each split into stages) with the runner's grouped seeds after
    some random steps, and return the first observations in global env order."""
    per_rank = num_envs // ranks
    envs = [StagedEnv(EnvSpec(name=name, num_envs=per_rank, stages=stages, kwargs=kwargs), rank=r)
            for r in range(ranks)]
    try:
        rng = np.random.default_rng(0)
        for env in envs:  # different histories before the reset
            env.reset(iteration_seeds(0, 0, per_rank))
            for _ in range(3):
                for stage, size in enumerate(env.sizes):
                    space = env.action_space
                    env.step(stage, rng.uniform(space.low, space.high, (size, *space.shape)).astype(np.float32))
        seeds = iteration_seeds(0, 1, num_envs, group_size)
        states = []
        for r, env in enumerate(envs):
            for message in env.reset(seeds[r * per_rank:(r + 1) * per_rank]):
                states.append(message["obs"]["state"])
        return np.concatenate(states)
    finally:
        for env in envs:
            env.close()


@pytest.mark.parametrize("name", ["gym:Pendulum-v1", "metaworld:reach-v3"])
def test_a_seed_group_starts_from_one_state_across_ranks_and_stages(name):
    if name.startswith("metaworld"):
        pytest.importorskip("metaworld")
    # 6 envs, 2 ranks of 3, each in 2 stages (2 + 1): group [2, 3] straddles the rank boundary,
    # group [0, 1] lies in one stage, group [4, 5] straddles rank 1's two stages.
    state = _grouped_first_obs(name, {}, num_envs=6, ranks=2, stages=2, group_size=2)
    for g in range(3):
        np.testing.assert_array_equal(state[2 * g], state[2 * g + 1])
    assert not np.array_equal(state[0], state[2]) and not np.array_equal(state[2], state[4])


def test_grpo_config_is_checked_before_anything_starts():
    with pytest.raises(ConfigError, match=r"algorithm.group_size=3 does not divide env.num_envs=4"):
        grpo_cfg(algorithm={"name": "grpo", "group_size": 3, "mini_batches": 2})
    with pytest.raises(ConfigError, match=r"algorithm.group_size=1 must be >= 2"):
        grpo_cfg(algorithm={"name": "grpo", "group_size": 1, "mini_batches": 2})
    with pytest.raises(ConfigError, match="algorithm.name"):
        grpo_cfg(algorithm={"name": "a2c"})
    with pytest.raises(ConfigError, match=r"^algorithm.grpo_baseline=false keeps the raw returns.*"
                                          r"set algorithm.grpo_norm_by_std=false"):
        grpo_cfg(algorithm={"name": "grpo", "group_size": 2, "mini_batches": 2, "grpo_baseline": False})
    grpo_cfg(algorithm={"name": "grpo", "group_size": 2, "mini_batches": 2, "grpo_baseline": False,
                        "grpo_norm_by_std": False})
    with pytest.raises(ConfigError, match=r"partial_rollout is for language-model generation"):
        grpo_cfg(algorithm={"name": "ppo", "asynchronous": {"max_staleness": 1, "partial_rollout": True}})
    grpo_cfg(algorithm={"name": "ppo", "group_size": 3, "mini_batches": 2})  # group_size is grpo's only
    spec = ppo_spec(grpo_cfg())
    assert not spec.critic and not spec.normalize_advantages  # group-normalised: used as they are
    assert ppo_spec(grpo_cfg(algorithm={"name": "ppo", "mini_batches": 2})).critic


def _trajectory(t=5, n=4):
    rewards = np.arange(t * n, dtype=np.float32).reshape(t, n) % 3
    terminated = np.zeros((t, n), bool)
    terminated[2, 1] = True  # env 1's first episode ends at step 2; steps 3, 4 are a new episode
    return {
        "obs": {"state": np.random.default_rng(0).normal(size=(t, n, 3)).astype(np.float32)},
        "actions": np.zeros((t, n, 1, 1), np.float32), "logprobs": np.zeros((t, n, 1), np.float32),
        "step_mask": np.ones((t, n, 1), bool), "values": np.zeros((t, n), np.float32),
        "rewards": rewards, "step_rewards": rewards[..., None], "terminated": terminated,
        "truncated": np.zeros((t, n), bool), "final_values": np.zeros((t, n), np.float32),
        "bootstrap_values": np.zeros(n, np.float32),
    }


def test_grpo_batch_carries_the_episode_mask_and_group_advantages():
    flow = EmbodiedFlow(grpo_cfg(), None, None, None)
    traj = _trajectory()
    traj["rewards"][:, 3] = traj["rewards"][:, 2]  # group (2, 3): equal returns, no signal
    batch, metrics = flow.advantages(traj)
    mask = batch["advantage_mask"].reshape(5, 4)
    assert mask.dtype == bool
    assert mask[:3].all() and not mask[3:, 1].any() and mask[:, [0, 2, 3]].all()
    adv = batch["advantages"].reshape(5, 4)
    returns = [traj["rewards"][:, 0].sum(), traj["rewards"][:3, 1].sum()]
    expected = (returns[0] - np.mean(returns)) / (np.std(returns, ddof=1) + 1e-6)
    np.testing.assert_allclose(adv[:, 0], expected, rtol=1e-5)  # one advantage for the whole episode
    np.testing.assert_allclose(adv[:3, 1], -expected, rtol=1e-5)
    assert (adv[3:, 1] == 0).all() and (adv[:, 2:] == 0).all()
    assert metrics["train/group_return_std_zero_frac"] == 0.5
    assert metrics["train/advantage_mask_frac"] == pytest.approx(18 / 20)
    assert "train/reward_scale" not in metrics  # no reward scaling for grpo
    assert flow.return_norm.rms.count == pytest.approx(1e-4)  # the PPO return normaliser was not fed

    ppo = EmbodiedFlow(grpo_cfg(algorithm={"name": "ppo", "mini_batches": 2}), None, None, None)
    batch, _ = ppo.advantages(_trajectory())
    assert batch["advantage_mask"].all()  # GAE trains on every decision


def _policy_and_batch():
    observation_spec, action_space = probe_env_specs("gym:Pendulum-v1", {})
    spec = PolicySpec(name="mlp_gaussian", options={"hidden": [8]}, normalize_obs=False)
    torch.manual_seed(0)
    model = spec.build(observation_spec, action_space)
    b = 16
    gen = torch.Generator().manual_seed(1)
    obs = {"state": torch.randn(b, 3, generator=gen)}
    with torch.no_grad():
        step = model.act(obs)
    batch = {"obs": obs, "actions": step.actions, "logprobs": step.logprobs,
             "step_mask": torch.ones(b, 1, dtype=torch.bool), "values": torch.zeros(b),
             "advantages": torch.randn(b, generator=gen), "returns": torch.randn(b, generator=gen),
             "advantage_mask": torch.arange(b) % 4 != 3}
    return spec, observation_spec, action_space, batch


def test_grpo_update_ignores_masked_decisions_and_trains_no_critic():
    spec, observation_spec, action_space, batch = _policy_and_batch()
    ppo = ppo_spec(grpo_cfg(algorithm={"name": "grpo", "group_size": 2, "epochs": 2, "mini_batches": 2,
                                       "entropy_coef": 0.01}))

    def train(batch):
        torch.manual_seed(0)
        model = spec.build(observation_spec, action_space)
        critic = [p.detach().clone() for p in model.policy.critic.parameters()]
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
        metrics = ppo_update(model, optimizer, batch, 0, ppo)
        for before, after in zip(critic, model.policy.critic.parameters()):
            assert torch.equal(before, after)  # no value loss: the critic never moves
        return metrics, torch.cat([p.detach().reshape(-1) for p in model.parameters()])

    metrics, weights = train(batch)
    assert "train/value_loss" not in metrics and "train/explained_variance" not in metrics
    assert metrics["train/logprob_mismatch"] < 1e-6  # still measured
    garbage = dict(batch)
    masked = ~batch["advantage_mask"]
    garbage["advantages"] = torch.where(masked, torch.full_like(batch["advantages"], 1e6), batch["advantages"])
    actions = batch["actions"].clone()
    actions[masked] = 5.0
    garbage["actions"] = actions
    _, weights_garbage = train(garbage)
    assert torch.equal(weights, weights_garbage)  # masked decisions contribute nothing
    no_mask = {k: v for k, v in batch.items() if k != "advantage_mask"}
    _, weights_all = train(no_mask)
    assert not torch.equal(weights, weights_all)


def test_grpo_on_multi_task_envs_gives_each_group_a_task_block():
    """A group shares its reset seed, so it must share its task: consecutive blocks of
    group_size envs run one task, every task as often; the evaluation undoes the blocks."""
    pytest.importorskip("metaworld")
    from infinirl.components.env_worker import EnvSpec
    from infinirl.runners.embodied import _check_one_task_per_group, _layout, eval_env_kwargs, task_block

    single = grpo_cfg(env={"name": "metaworld:reach-v3", "num_envs": 4})
    _check_one_task_per_group(single)
    assert task_block(single) == 1
    two_tasks = {"name": "metaworld:reach-v3,push-v3", "num_envs": 8, "kwargs": {"obs_mode": "state"}}
    two = grpo_cfg(env=two_tasks)
    _check_one_task_per_group(two)
    assert task_block(two) == 2 and eval_env_kwargs(2, {"terminate_on_success": True}) == {
        "terminate_on_success": True, "task_block": 1}
    assert task_block(grpo_cfg(env=two_tasks, algorithm={"name": "ppo", "mini_batches": 2})) == 1

    class OneRank:
        def relation(self, a, b):
            return "collocated"

        def world_size(self, role):
            return 1

    _, spec = _layout(two, OneRank())
    assert spec.kwargs["task_block"] == 2
    seeds = iteration_seeds(0, 3, 8, group_size=2)
    with spec.build(8) as env:
        obs = env.reset(seeds=seeds)
        assert env.task_names == ["reach-v3", "reach-v3", "push-v3", "push-v3"] * 2
        for group in range(4):  # one task and one layout a group
            np.testing.assert_array_equal(obs["state"][2 * group], obs["state"][2 * group + 1])
    with EnvSpec(**{**spec.__dict__, "kwargs": eval_env_kwargs(2, spec.kwargs)}).build(4) as env:
        assert env.task_names == ["reach-v3", "push-v3"] * 2
    with pytest.raises(ConfigError, match="multiple of 4"):
        _check_one_task_per_group(grpo_cfg(env={"name": "metaworld:reach-v3,push-v3", "num_envs": 6}))
    with pytest.raises(ConfigError, match="multiples of 4"):
        _layout(grpo_cfg(env=two_tasks, rollout={"pipeline_stages": 4}), OneRank())



@pytest.mark.parametrize("name", ["grpo_metaworld_reach", "grpo_openvla_oft_libero"])
def test_shipped_grpo_configs_run_one_task(name):
    """The multi-task refusal above must not hit a shipped config (it would only show once a
    user's 7B checkpoint had loaded in the driver)."""
    from infinirl.cli import build_config
    from infinirl.runners.embodied import _check_one_task_per_group

    _, cfg = build_config(name, ["policy.kwargs.checkpoint=/unused"] if "libero" in name else [])
    pytest.importorskip("libero" if "libero" in name else "metaworld")
    _check_one_task_per_group(cfg)

def test_grpo_action_level_with_chunks_masks_per_action_and_trains():
    cfg = grpo_cfg(policy={"name": "mlp_gaussian", "kwargs": {"hidden": [8]}, "chunk": 2, "normalize_obs": False},
                   algorithm={"name": "grpo", "group_size": 2, "epochs": 1, "mini_batches": 2, "gae_level": "action"})
    traj = _trajectory()
    step_rewards = np.stack([traj["rewards"], traj["rewards"]], axis=-1)
    traj.update(step_rewards=step_rewards, rewards=step_rewards.sum(-1), actions=np.zeros((5, 4, 2, 1), np.float32),
                logprobs=np.zeros((5, 4, 2), np.float32), step_mask=np.ones((5, 4, 2), bool))
    traj["step_mask"][2, 1, 1] = False  # env 1's episode ended after the chunk's first action
    batch, _ = EmbodiedFlow(cfg, None, None, None).advantages(traj)
    mask = batch["advantage_mask"].reshape(5, 4, 2)
    assert batch["advantages"].shape == (20, 2) and mask[:3, 1].all() and not mask[3:, 1].any()

    observation_spec, action_space = probe_env_specs("gym:Pendulum-v1", {})
    spec = PolicySpec(name="mlp_gaussian", options={"hidden": [8]}, chunk=2, normalize_obs=False)
    model = spec.build(observation_spec, action_space)
    tensors = {k: ({kk: torch.from_numpy(vv) for kk, vv in v.items()} if isinstance(v, dict) else torch.from_numpy(v))
               for k, v in batch.items()}
    with torch.no_grad():
        tensors["logprobs"] = model(tensors["obs"], tensors["actions"], None, False)[0]
    metrics = ppo_update(model, torch.optim.Adam(model.parameters()), tensors, 0, ppo_spec(cfg))
    assert metrics["train/logprob_mismatch"] < 1e-6 and np.isfinite(metrics["train/policy_loss"])


def _ppo_flow(**algorithm):
    return EmbodiedFlow(grpo_cfg(algorithm={"name": "ppo", "mini_batches": 2, **algorithm}), None, None, None)


def test_a_step_both_terminated_and_out_of_time_is_not_bootstrapped():
    """gymnasium's TimeLimit sets truncated whatever terminated says: the task ended, V(final obs)
    must not stand in for what follows."""
    both = _trajectory()
    both["truncated"][2, 1] = True
    both["final_values"][2, 1] = 100.0
    plain = _ppo_flow(normalize_rewards=False).advantages(_trajectory())[0]["advantages"]
    np.testing.assert_array_equal(_ppo_flow(normalize_rewards=False).advantages(both)[0]["advantages"], plain)


def test_action_level_gae_ends_an_episode_on_the_action_it_ended_on():
    """An env stops at the action its episode ended on; the chunk's later actions never ran and must
    not sit between that action and the episode's end."""
    flow = EmbodiedFlow(grpo_cfg(policy={"name": "mlp_gaussian", "kwargs": {"hidden": [8]}, "chunk": 2},
                                 algorithm={"name": "ppo", "mini_batches": 2, "gae_level": "action",
                                            "normalize_rewards": False}), None, None, None)
    traj = _trajectory()
    step_rewards = np.stack([traj["rewards"], np.zeros_like(traj["rewards"])], axis=-1)
    traj.update(step_rewards=step_rewards, rewards=step_rewards.sum(-1), values=np.full((5, 4), 10.0, np.float32),
                actions=np.zeros((5, 4, 2, 1), np.float32), logprobs=np.zeros((5, 4, 2), np.float32),
                step_mask=np.ones((5, 4, 2), bool))
    traj["step_mask"][2, 1, 1] = False  # env 1's episode ended on the chunk's first action
    advantages = flow.advantages(traj)[0]["advantages"].reshape(5, 4, 2)
    assert advantages[2, 1, 0] == pytest.approx(traj["step_rewards"][2, 1, 0] - 10.0)


def test_the_running_return_restarts_with_every_iteration():
    """Each iteration resets every env, so the reward scale's running return must not carry on."""
    flow = _ppo_flow()
    flow.advantages(_trajectory())
    assert not flow.return_norm.returns.any()
