"""Embodied (env rollout) estimators against float64 loop references, plus hand-made cases."""

import dataclasses
import math

import pytest
import torch

from infinirl.algorithms import (
    ADVANTAGES,
    EnvAdvantageInputs,
    TokenAdvantageInputs,
    embodied_gae,
    embodied_grpo,
    normalize_per_task,
)

SEEDS = [0, 1, 2]


def ref_gae_series(rewards, values, dones, truncs, final_values, bootstrap, gamma, lam):
    """rewards etc. as nested lists [S][N]; returns advantages [S][N]."""
    steps, envs = len(rewards), len(rewards[0])
    out = [[0.0] * envs for _ in range(steps)]
    for n in range(envs):
        next_adv = 0.0
        for s in reversed(range(steps)):
            if truncs[s][n]:
                next_value, cont = final_values[s][n], 0.0
            elif dones[s][n]:
                next_value, cont = 0.0, 0.0
            else:
                next_value = values[s + 1][n] if s + 1 < steps else bootstrap[n]
                cont = 1.0
            delta = rewards[s][n] + gamma * next_value - values[s][n]
            next_adv = delta + gamma * lam * cont * next_adv
            out[s][n] = next_adv
    return out


def random_env_inputs(seed, *, steps=6, envs=4, chunk=None, per_action_dones=False):
    gen = torch.Generator().manual_seed(seed)
    shape = (steps, envs) if chunk is None else (steps, envs, chunk)
    done_shape = shape if per_action_dones else (steps, envs)
    dones = torch.rand(done_shape, generator=gen) < 0.25
    truncations = dones & (torch.rand(done_shape, generator=gen) < 0.5)
    return EnvAdvantageInputs(
        rewards=torch.randn(shape, generator=gen, dtype=torch.float64),
        dones=dones,
        values=torch.randn(shape if chunk is not None else (steps, envs), generator=gen,
                           dtype=torch.float64),
        bootstrap_values=torch.randn(envs, generator=gen, dtype=torch.float64),
        truncations=truncations,
        final_values=torch.randn(done_shape, generator=gen, dtype=torch.float64),
        group_size=2,
    )


def test_truncation_bootstraps_and_termination_does_not():
    ones = torch.ones(3, 2, dtype=torch.float64)
    dones = torch.tensor([[False, False], [True, True], [False, False]])
    truncations = torch.tensor([[False, False], [False, True], [False, False]])
    final_values = torch.zeros(3, 2, dtype=torch.float64)
    final_values[1, 1] = 10.0
    inputs = EnvAdvantageInputs(
        rewards=ones, dones=dones, values=2 * ones,
        bootstrap_values=torch.tensor([4.0, 4.0], dtype=torch.float64),
        truncations=truncations, final_values=final_values,
    )
    out = embodied_gae(inputs, gamma=0.5, lam=1.0)
    # env 0 terminated at step 1:  A = [-0.5, -1, 1];  env 1 truncated (V(final)=10): A = [2, 4, 1]
    expected = torch.tensor([[-0.5, 2.0], [-1.0, 4.0], [1.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(out.advantages, expected)
    torch.testing.assert_close(out.returns, expected + 2.0)


@pytest.mark.parametrize("chunk", [None, 3])
@pytest.mark.parametrize("seed", SEEDS)
def test_bootstrap_of_an_env_that_ended_on_the_last_step_is_unused(seed, chunk):
    """Why a rollout may skip resetting envs on its last step: an env whose episode ended there
    has no successor in the rollout, so its ``bootstrap_values`` entry (V of an observation from
    a reset that then never happens) must not reach any advantage or return."""
    inputs = random_env_inputs(seed, chunk=chunk)
    inputs.dones[-1, :2] = True  # envs 0 and 1 end on the last decision (one truncated)
    inputs.truncations[-1, 0], inputs.truncations[-1, 1] = True, False
    levels = ["chunk"] if chunk is None else ["action"]  # (random_env_inputs gives [T, N, C] values with a chunk)
    for level in levels:
        base = embodied_gae(inputs, gamma=0.9, lam=0.8, level=level)
        changed = inputs.bootstrap_values.clone()
        changed[:2] += 1e3
        moved = embodied_gae(dataclasses.replace(inputs, bootstrap_values=changed), gamma=0.9, lam=0.8, level=level)
        torch.testing.assert_close(moved.advantages, base.advantages, rtol=0, atol=0)
        torch.testing.assert_close(moved.returns, base.returns, rtol=0, atol=0)
        changed[2:] += 1e3  # control: envs that did not end do bootstrap from it
        moved = embodied_gae(dataclasses.replace(inputs, bootstrap_values=changed), gamma=0.9, lam=0.8, level=level)
        assert not torch.equal(moved.advantages[-1], base.advantages[-1])


def test_truncation_without_final_values_is_an_error():
    inputs = EnvAdvantageInputs(
        rewards=torch.zeros(2, 1), dones=torch.tensor([[True], [False]]), values=torch.zeros(2, 1),
        bootstrap_values=torch.zeros(1), truncations=torch.tensor([[True], [False]]),
    )
    with pytest.raises(ValueError, match="final"):
        embodied_gae(inputs)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("gamma,lam", [(0.99, 0.95), (0.8, 1.0)])
def test_step_level_gae_matches_reference(seed, gamma, lam):
    inputs = random_env_inputs(seed)
    out = ADVANTAGES.get("embodied_gae")(inputs, gamma=gamma, lam=lam)
    expected = ref_gae_series(
        inputs.rewards.tolist(), inputs.values.tolist(), inputs.dones.tolist(),
        inputs.truncations.tolist(), inputs.final_values.tolist(),
        inputs.bootstrap_values.tolist(), gamma, lam,
    )
    torch.testing.assert_close(out.advantages, torch.tensor(expected, dtype=torch.float64))
    torch.testing.assert_close(out.returns, out.advantages + inputs.values)


@pytest.mark.parametrize("seed", SEEDS)
def test_chunk_level_gae_sums_rewards_over_the_chunk(seed):
    inputs = random_env_inputs(seed, chunk=3)
    chunk_values = inputs.values.sum(dim=-1)  # any [T, N] critic output
    inputs = EnvAdvantageInputs(
        rewards=inputs.rewards, dones=inputs.dones, values=chunk_values,
        bootstrap_values=inputs.bootstrap_values, truncations=inputs.truncations,
        final_values=inputs.final_values,
    )
    out = embodied_gae(inputs, gamma=0.9, lam=0.9, level="chunk")
    summed = [[sum(chunk) for chunk in row] for row in inputs.rewards.tolist()]
    expected = ref_gae_series(
        summed, chunk_values.tolist(), inputs.dones.tolist(), inputs.truncations.tolist(),
        inputs.final_values.tolist(), inputs.bootstrap_values.tolist(), 0.9, 0.9,
    )
    assert out.advantages.shape == (6, 4)
    torch.testing.assert_close(out.advantages, torch.tensor(expected, dtype=torch.float64))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("per_action_dones", [False, True])
def test_action_level_gae_unrolls_the_chunk(seed, per_action_dones):
    chunk = 3
    inputs = random_env_inputs(seed, chunk=chunk, per_action_dones=per_action_dones)
    out = embodied_gae(inputs, gamma=0.9, lam=0.8, level="action")
    steps, envs = 6, 4

    def flat(tensor, end_of_chunk):
        rows = []
        for t in range(steps):
            for c in range(chunk):
                row = []
                for n in range(envs):
                    if tensor.dim() == 3:
                        row.append(tensor[t, n, c].item())
                    else:
                        on_this_action = c == chunk - 1 or not end_of_chunk
                        row.append(tensor[t, n].item() if on_this_action else 0)
                rows.append(row)
        return rows

    flat_adv = ref_gae_series(
        flat(inputs.rewards, False), flat(inputs.values, False), flat(inputs.dones, True),
        flat(inputs.truncations, True), flat(inputs.final_values, True),
        inputs.bootstrap_values.tolist(), 0.9, 0.8,
    )
    expected = torch.zeros(steps, envs, chunk, dtype=torch.float64)
    for t in range(steps):
        for c in range(chunk):
            for n in range(envs):
                expected[t, n, c] = flat_adv[t * chunk + c][n]
    torch.testing.assert_close(out.advantages, expected)
    torch.testing.assert_close(out.returns, expected + inputs.values)


def test_chunk_level_with_per_action_dones_and_no_truncations():
    rewards = torch.ones(2, 1, 3, dtype=torch.float64)
    dones = torch.tensor([[[False, True, False]], [[False, False, False]]])
    inputs = EnvAdvantageInputs(
        rewards=rewards, dones=dones, values=torch.zeros(2, 1, dtype=torch.float64),
        bootstrap_values=torch.tensor([10.0], dtype=torch.float64),
    )
    out = embodied_gae(inputs, gamma=0.5, lam=1.0)
    # chunk 0 ends the episode (terminated): A0 = 3; chunk 1 bootstraps: A1 = 3 + 0.5 * 10 = 8
    torch.testing.assert_close(out.advantages, torch.tensor([[3.0], [8.0]], dtype=torch.float64))


def test_gae_level_errors():
    inputs = random_env_inputs(0)
    with pytest.raises(ValueError, match="level"):
        embodied_gae(inputs, level="token")
    with pytest.raises(ValueError, match="action-level GAE needs per-action rewards"):
        embodied_gae(inputs, level="action")
    with pytest.raises(ValueError, match="bootstrap_values"):
        embodied_gae(EnvAdvantageInputs(rewards=torch.zeros(2, 1), dones=torch.zeros(2, 1),
                                        values=torch.zeros(2, 1)))
    with pytest.raises(TypeError, match="EnvAdvantageInputs"):
        embodied_gae(TokenAdvantageInputs(torch.zeros(2), torch.ones(2, 2)))


def test_env_inputs_validate_shapes():
    with pytest.raises(ValueError, match="dones must be"):
        EnvAdvantageInputs(rewards=torch.zeros(3, 2), dones=torch.zeros(3, 4))
    with pytest.raises(ValueError, match="bootstrap_values"):
        EnvAdvantageInputs(rewards=torch.zeros(3, 2), dones=torch.zeros(3, 2),
                           bootstrap_values=torch.zeros(3))
    with pytest.raises(ValueError, match="truncations must be shaped like dones"):
        EnvAdvantageInputs(rewards=torch.zeros(3, 2, 2), dones=torch.zeros(3, 2),
                           truncations=torch.zeros(3, 2, 2))


# --- embodied GRPO -----------------------------------------------------------------------------


def ref_embodied_grpo(rewards, dones, group_of_env, eps, norm_by_std):
    """rewards/dones [S][N] lists (already per action if chunked)."""
    steps, envs = len(rewards), len(rewards[0])
    returns, first = [0.0] * envs, [[False] * envs for _ in range(steps)]
    for n in range(envs):
        for s in range(steps):
            first[s][n] = True
            returns[n] += rewards[s][n]
            if dones[s][n]:
                break
    scores = [0.0] * envs
    groups = {}
    for n, g in enumerate(group_of_env):
        groups.setdefault(g, []).append(n)
    for members in groups.values():
        vals = [returns[n] for n in members]
        mean = sum(vals) / len(vals)
        var = sum((v - mean) ** 2 for v in vals) / (len(vals) - 1) if len(vals) > 1 else 0.0
        std = math.sqrt(var)
        for n in members:
            scores[n] = (returns[n] - mean) / (std + eps) if norm_by_std else returns[n] - mean
    adv = [[scores[n] if first[s][n] else 0.0 for n in range(envs)] for s in range(steps)]
    ret = [[returns[n] if first[s][n] else 0.0 for n in range(envs)] for s in range(steps)]
    return adv, ret, first


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("norm_by_std", [True, False])
def test_embodied_grpo_matches_reference(seed, norm_by_std):
    inputs = random_env_inputs(seed, envs=6)
    out = embodied_grpo(inputs, eps=1e-6, norm_by_std=norm_by_std)
    ends = (inputs.dones | inputs.truncations).tolist()
    adv, ret, first = ref_embodied_grpo(inputs.rewards.tolist(), ends, [n // 2 for n in range(6)],
                                        1e-6, norm_by_std)
    torch.testing.assert_close(out.advantages, torch.tensor(adv, dtype=torch.float64))
    torch.testing.assert_close(out.returns, torch.tensor(ret, dtype=torch.float64))
    assert torch.equal(out.mask, torch.tensor(first))


def test_embodied_grpo_hand_computed_with_group_ids_and_chunks():
    # 2 steps x 4 envs x chunk 2; envs 0 and 2 share a reset state, envs 1 and 3 share another.
    rewards = torch.zeros(2, 4, 2, dtype=torch.float64)
    rewards[0, 0, 1] = 1.0  # env 0 succeeds in the first chunk and terminates...
    rewards[1, 0, 0] = 5.0  # ...so this reward belongs to its next episode and is ignored
    rewards[1, 1, 1] = 1.0
    rewards[1, 3, 1] = 1.0
    dones = torch.tensor([[True, False, False, False], [False, True, True, True]])
    out = embodied_grpo(EnvAdvantageInputs(rewards=rewards, dones=dones,
                                           group_ids=torch.tensor([7, 3, 7, 3])))
    # returns: env0 1, env1 1, env2 0, env3 1. Group {0,2}: +-1/(sqrt(0.5)+eps); group {1,3}: 0.
    a = 0.5 / (math.sqrt(0.5) + 1e-6)
    assert out.advantages.shape == (2, 4, 2)
    torch.testing.assert_close(out.advantages[0, :, 0], torch.tensor([a, 0.0, -a, 0.0],
                                                                     dtype=torch.float64))
    assert torch.equal(out.advantages[1, 0], torch.zeros(2, dtype=torch.float64))
    assert torch.equal(out.mask[:, 0], torch.tensor([[True, True], [False, False]]))
    assert bool(out.mask[:, 1:].all())


def test_embodied_grpo_all_equal_returns_give_zero():
    inputs = EnvAdvantageInputs(rewards=torch.ones(4, 4), dones=torch.zeros(4, 4), group_size=4)
    assert torch.equal(embodied_grpo(inputs).advantages, torch.zeros(4, 4))


@pytest.mark.parametrize("seed", SEEDS)
def test_embodied_grpo_without_baseline_is_the_raw_first_episode_return(seed):
    inputs = random_env_inputs(seed, envs=6)
    out = embodied_grpo(inputs, norm_by_std=False, baseline=False)
    ends = (inputs.dones | inputs.truncations).tolist()
    _, ret, first = ref_embodied_grpo(inputs.rewards.tolist(), ends, [n // 2 for n in range(6)], 1e-6, False)
    torch.testing.assert_close(out.advantages, torch.tensor(ret, dtype=torch.float64))
    assert torch.equal(out.mask, torch.tensor(first))
    with pytest.raises(ValueError, match="baseline=False keeps the raw returns; it needs norm_by_std=False"):
        embodied_grpo(inputs, baseline=False)


@pytest.mark.parametrize("seed", SEEDS)
def test_embodied_grpo_per_episode_weighs_every_episode_the_same(seed):
    inputs = random_env_inputs(seed, envs=6)
    out = embodied_grpo(inputs, norm_by_std=False, baseline=False, per_episode=True)
    ends = (inputs.dones | inputs.truncations).tolist()
    _, ret, first = ref_embodied_grpo(inputs.rewards.tolist(), ends, [n // 2 for n in range(6)], 1e-6, False)
    lengths = [sum(first[s][n] for s in range(len(first))) for n in range(6)]
    mean_length = sum(lengths) / 6
    expected = [[ret[s][n] * mean_length / lengths[n] for n in range(6)] for s in range(len(ret))]
    torch.testing.assert_close(out.advantages, torch.tensor(expected, dtype=torch.float64))
    # each episode's advantages sum to its return times the mean length, whatever its own length
    totals = out.advantages.sum(0)
    returns = torch.tensor([ret[0][n] for n in range(6)], dtype=torch.float64)
    torch.testing.assert_close(totals, returns * mean_length)


# --- advantages normalised within each task -------------------------------------------------------


def _per_task_reference(advantages, env_tasks, mask):
    """Slow float64 reference: every task's entries (its envs' columns, inside the mask) shifted
    and scaled to mean 0, std 1 (Bessel); entries outside the mask unchanged."""
    out = advantages.double().clone()
    for task in sorted(set(env_tasks.tolist())):
        cells = [(t, n) + rest for t in range(advantages.shape[0]) for n in range(advantages.shape[1])
                 if int(env_tasks[n]) == task
                 for rest in ([()] if advantages.dim() == 2 else [(c,) for c in range(advantages.shape[2])])
                 if bool(mask[(t, n) + rest])]
        values = torch.tensor([float(advantages[cell]) for cell in cells], dtype=torch.float64)
        mean = values.mean()
        std = values.std() if len(values) > 1 else torch.tensor(0.0, dtype=torch.float64)
        for cell in cells:
            out[cell] = (float(advantages[cell]) - mean) / (std + 1e-8)
    return out


@pytest.mark.parametrize("shape", [(5, 6), (4, 6, 3)])
def test_per_task_normalisation_matches_a_float64_reference(shape):
    generator = torch.Generator().manual_seed(0)
    advantages = torch.randn(*shape, generator=generator) * torch.tensor([1.0, 5.0, 0.2] * 2).reshape(
        1, 6, *([1] * (len(shape) - 2)))
    env_tasks = torch.tensor([0, 1, 2, 0, 1, 2])
    mask = torch.rand(*shape, generator=generator) > 0.2
    out = normalize_per_task(advantages, env_tasks, mask)
    torch.testing.assert_close(out.double(), _per_task_reference(advantages, env_tasks, mask), rtol=1e-5, atol=1e-5)
    for task in range(3):  # each task's scale is now 1, whatever it was
        cells = out[:, env_tasks == task][mask[:, env_tasks == task]]
        assert abs(float(cells.mean())) < 1e-5 and abs(float(cells.std()) - 1.0) < 1e-4


def test_per_task_normalisation_is_invariant_to_the_envs_order_and_to_each_tasks_scale():
    generator = torch.Generator().manual_seed(1)
    advantages = torch.randn(8, 4, generator=generator)
    env_tasks = torch.tensor([0, 1, 0, 1])
    out = normalize_per_task(advantages, env_tasks)
    order = torch.tensor([3, 0, 2, 1])
    torch.testing.assert_close(normalize_per_task(advantages[:, order], env_tasks[order]), out[:, order])
    scaled = advantages * torch.tensor([10.0, 0.1, 10.0, 0.1]) + torch.tensor([3.0, -2.0, 3.0, -2.0])
    torch.testing.assert_close(normalize_per_task(scaled, env_tasks), out, rtol=1e-4, atol=1e-4)


def test_per_task_normalisation_names_bad_shapes():
    with pytest.raises(ValueError, match=r"env_tasks must be \[N\]=\(4,\)"):
        normalize_per_task(torch.zeros(3, 4), torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="mask must have the advantages' shape"):
        normalize_per_task(torch.zeros(3, 4), torch.zeros(4, dtype=torch.long), torch.ones(3, 5, dtype=torch.bool))


def ref_action_returns_with_chunk_values(rewards, dones, truncs, final_values, values, bootstrap, gamma, lam):
    """Action-level lambda-returns when the critic gives one value per chunk, written forwards:
    from action ``c`` of chunk ``t`` the discounted rewards to the chunk's end, then
    ``gamma^(C-c) [(1 - lam) V_{t+1} + lam G_{t+1}]`` (G_{t+1} the return from the next chunk's
    first action); an episode end at action ``k`` stops the sum there (plus ``gamma^(k-c+1)
    V(final)`` for a truncation). Lists: rewards/dones/truncs/final_values [T][N][C], values
    [T][N], bootstrap [N]. Returns G [T][N][C]."""
    steps, envs, chunk = len(rewards), len(rewards[0]), len(rewards[0][0])
    out = [[[0.0] * chunk for _ in range(envs)] for _ in range(steps)]
    for n in range(envs):
        after = bootstrap[n]  # lambda-mixture the last chunk's end bootstraps from
        for t in reversed(range(steps)):
            for c in range(chunk):
                total, discount, ended = 0.0, 1.0, False
                for k in range(c, chunk):
                    total += discount * rewards[t][n][k]
                    discount *= gamma
                    if dones[t][n][k] or truncs[t][n][k]:
                        total += discount * final_values[t][n][k] if truncs[t][n][k] else 0.0
                        ended = True
                        break
                out[t][n][c] = total if ended else total + discount * after
            after = (1 - lam) * values[t][n] + lam * out[t][n][0]
    return out


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("per_action_dones", [False, True])
def test_action_level_gae_with_one_value_per_chunk_matches_the_forward_lambda_return(seed, per_action_dones):
    chunk, steps, envs = 3, 6, 4
    full = random_env_inputs(seed, chunk=chunk, per_action_dones=per_action_dones)
    chunk_values = full.values[..., 0].clone()
    inputs = dataclasses.replace(full, values=chunk_values)
    out = embodied_gae(inputs, gamma=0.9, lam=0.8, level="action")

    def per_action(tensor):
        if tensor.dim() == 3:
            return tensor.tolist()
        placed = torch.zeros(steps, envs, chunk, dtype=tensor.dtype)
        placed[..., -1] = tensor
        return placed.tolist()

    returns = ref_action_returns_with_chunk_values(
        inputs.rewards.tolist(), per_action(inputs.dones), per_action(inputs.truncations),
        per_action(inputs.final_values), chunk_values.tolist(), inputs.bootstrap_values.tolist(), 0.9, 0.8)
    returns = torch.tensor(returns, dtype=torch.float64)
    torch.testing.assert_close(out.returns, returns)
    torch.testing.assert_close(out.advantages, returns - chunk_values[..., None])


def test_a_perfect_chunk_critic_is_a_fixed_point_of_action_level_gae():
    """Sparse reward at the episode's end, chunks of 50 (as a VLA's): with the true chunk values
    the value targets are those values and the first action's advantage is 0 in every chunk (a
    shared value used as every action's bootstrap would pull the early chunks' targets far below)."""
    chunk, steps, gamma = 50, 6, 0.99
    rewards = torch.zeros(steps, 1, chunk, dtype=torch.float64)
    rewards[-1, 0, -1] = 1.0
    dones = torch.zeros(steps, 1, dtype=torch.bool)
    dones[-1, 0] = True
    true_values = torch.tensor([[gamma ** (chunk * (steps - 1 - t) + chunk - 1)] for t in range(steps)],
                               dtype=torch.float64)
    inputs = EnvAdvantageInputs(rewards=rewards, dones=dones, values=true_values,
                                bootstrap_values=torch.zeros(1, dtype=torch.float64))
    out = embodied_gae(inputs, gamma=gamma, lam=0.95, level="action")
    torch.testing.assert_close(out.returns[..., 0], true_values)
    torch.testing.assert_close(out.advantages[..., 0], torch.zeros_like(true_values))
