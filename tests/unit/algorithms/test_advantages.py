"""Token-level advantage estimators against slow float64 loop references, plus hand-made cases."""

import math

import pytest
import torch

from infinirl.algorithms import (
    ADVANTAGES,
    TokenAdvantageInputs,
    compute_advantages,
    gae,
    grpo,
    reinforce_pp,
    rloo,
)

SEEDS = [0, 1, 2, 3]


# --- slow references: python loops over python floats ------------------------------------------


def valid_positions(mask_row):
    return [t for t, m in enumerate(mask_row.tolist()) if m]


def ref_token_rewards(rewards, mask, token_rewards):
    """Per row: (position, reward) for each valid token; the sequence reward on the last one."""
    rows = []
    for i in range(mask.shape[0]):
        positions = valid_positions(mask[i])
        row = []
        for k, t in enumerate(positions):
            r = 0.0 if token_rewards is None else float(token_rewards[i, t])
            if k == len(positions) - 1:
                r += float(rewards[i])
            row.append((t, r))
        rows.append(row)
    return rows


def ref_gae(rewards, values, mask, token_rewards, gamma, lam):
    advantages = torch.zeros(mask.shape, dtype=torch.float64)
    returns = torch.zeros(mask.shape, dtype=torch.float64)
    for i, row in enumerate(ref_token_rewards(rewards, mask, token_rewards)):
        next_value, next_adv = 0.0, 0.0
        for t, r in reversed(row):
            v = float(values[i, t])
            delta = r + gamma * next_value - v
            adv = delta + gamma * lam * next_adv
            advantages[i, t], returns[i, t] = adv, adv + v
            next_value, next_adv = v, adv
    return advantages, returns


def ref_groups(group_labels):
    groups = {}
    for i, g in enumerate(group_labels):
        groups.setdefault(g, []).append(i)
    return groups


def ref_grpo_scores(rewards, group_labels, eps, norm_by_std):
    scores = [0.0] * len(rewards)
    for members in ref_groups(group_labels).values():
        values = [float(rewards[i]) for i in members]
        mean = sum(values) / len(values)
        var = sum((v - mean) ** 2 for v in values) / (len(values) - 1) if len(values) > 1 else 0.0
        for i in members:
            centred = float(rewards[i]) - mean
            scores[i] = centred / (math.sqrt(var) + eps) if norm_by_std else centred
    return scores


def ref_rloo_scores(rewards, group_labels):
    scores = [0.0] * len(rewards)
    for members in ref_groups(group_labels).values():
        for i in members:
            others = [float(rewards[j]) for j in members if j != i]
            scores[i] = float(rewards[i]) - sum(others) / len(others) if others else 0.0
    return scores


def ref_broadcast(scores, mask):
    out = torch.zeros(mask.shape, dtype=torch.float64)
    for i in range(mask.shape[0]):
        for t in valid_positions(mask[i]):
            out[i, t] = scores[i]
    return out


def ref_reinforce_pp(rewards, mask, token_rewards, gamma, eps):
    returns = torch.zeros(mask.shape, dtype=torch.float64)
    for i, row in enumerate(ref_token_rewards(rewards, mask, token_rewards)):
        running = 0.0
        for t, r in reversed(row):
            running = r + gamma * running
            returns[i, t] = running
    valid = [(i, t) for i in range(mask.shape[0]) for t in valid_positions(mask[i])]
    mean = sum(float(returns[i, t]) for i, t in valid) / len(valid)
    var = sum((float(returns[i, t]) - mean) ** 2 for i, t in valid) / len(valid)
    advantages = torch.zeros(mask.shape, dtype=torch.float64)
    for i, t in valid:
        advantages[i, t] = (float(returns[i, t]) - mean) / math.sqrt(var + eps)
    return advantages, returns


# --- random inputs -----------------------------------------------------------------------------


def random_inputs(factory, seed, *, batch=8, width=10, group_size=4, with_token_rewards=True):
    gen = torch.Generator().manual_seed(seed)
    mask = factory(gen, batch, width, empty_rows=1)
    rewards = torch.randn(batch, generator=gen, dtype=torch.float64)
    values = torch.randn(batch, width, generator=gen, dtype=torch.float64)
    token_rewards = (
        0.1 * torch.randn(batch, width, generator=gen, dtype=torch.float64)
        if with_token_rewards
        else None
    )
    return TokenAdvantageInputs(
        rewards=rewards, response_mask=mask, values=values, token_rewards=token_rewards,
        group_size=group_size,
    )


# --- GAE ---------------------------------------------------------------------------------------


def test_gae_hand_computed_example():
    # One row: prompt token at 0, response tokens at 1..3, padding at 4. gamma = 0.5, lam = 0.5.
    mask = torch.tensor([[0, 1, 1, 1, 0]], dtype=torch.float64)
    values = torch.tensor([[9.0, 1.0, 2.0, 3.0, 9.0]], dtype=torch.float64)
    inputs = TokenAdvantageInputs(rewards=torch.tensor([4.0], dtype=torch.float64),
                                  response_mask=mask, values=values)
    out = gae(inputs, gamma=0.5, lam=0.5)
    # t=3: delta = 4 + 0 - 3 = 1, A = 1
    # t=2: delta = 0 + 0.5*3 - 2 = -0.5, A = -0.5 + 0.25*1 = -0.25
    # t=1: delta = 0 + 0.5*2 - 1 = 0, A = 0 + 0.25*(-0.25) = -0.0625
    expected = torch.tensor([[0.0, -0.0625, -0.25, 1.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(out.advantages, expected)
    torch.testing.assert_close(out.returns, torch.tensor([[0.0, 0.9375, 1.75, 4.0, 0.0]],
                                                         dtype=torch.float64))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("gamma,lam", [(1.0, 0.95), (0.9, 1.0), (0.7, 0.3)])
def test_gae_matches_reference(response_mask_factory, seed, gamma, lam):
    inputs = random_inputs(response_mask_factory, seed)
    out = compute_advantages("gae", inputs, gamma=gamma, lam=lam)
    adv, ret = ref_gae(inputs.rewards, inputs.values, inputs.response_mask, inputs.token_rewards,
                       gamma, lam)
    torch.testing.assert_close(out.advantages, adv)
    torch.testing.assert_close(out.returns, ret)
    assert torch.equal(out.mask, inputs.response_mask)


def test_gae_skips_masked_gap_tokens():
    """A tool-output gap between two generated spans is transparent: same result as without it."""
    values = torch.tensor([[0.0, 0.5, 7.0, 7.0, -0.5, 0.0]], dtype=torch.float64)
    with_gap = torch.tensor([[0, 1, 0, 0, 1, 0]], dtype=torch.float64)
    compact_values = torch.tensor([[0.0, 0.5, -0.5]], dtype=torch.float64)
    compact = torch.tensor([[0, 1, 1]], dtype=torch.float64)
    reward = torch.tensor([1.0], dtype=torch.float64)
    gapped = gae(TokenAdvantageInputs(reward, with_gap, values=values), gamma=0.9, lam=0.8)
    plain = gae(TokenAdvantageInputs(reward, compact, values=compact_values), gamma=0.9, lam=0.8)
    torch.testing.assert_close(gapped.advantages[0, [1, 4]], plain.advantages[0, [1, 2]])
    assert gapped.advantages[0, 2:4].abs().sum() == 0


def test_gae_requires_values():
    inputs = TokenAdvantageInputs(rewards=torch.zeros(2), response_mask=torch.ones(2, 3))
    with pytest.raises(ValueError, match="critic values"):
        gae(inputs)


# --- GRPO / Dr.GRPO / RLOO ---------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("norm_by_std", [True, False])
def test_grpo_matches_reference(response_mask_factory, seed, norm_by_std):
    inputs = random_inputs(response_mask_factory, seed)
    out = grpo(inputs, eps=1e-6, norm_by_std=norm_by_std)
    labels = [i // 4 for i in range(8)]
    scores = ref_grpo_scores(inputs.rewards, labels, 1e-6, norm_by_std)
    torch.testing.assert_close(out.advantages, ref_broadcast(scores, inputs.response_mask))
    torch.testing.assert_close(
        out.returns, ref_broadcast(inputs.rewards.tolist(), inputs.response_mask)
    )


@pytest.mark.parametrize("seed", SEEDS)
def test_dr_grpo_is_grpo_without_std(response_mask_factory, seed):
    inputs = random_inputs(response_mask_factory, seed)
    out = compute_advantages("dr_grpo", inputs)
    scores = ref_grpo_scores(inputs.rewards, [i // 4 for i in range(8)], 0.0, norm_by_std=False)
    torch.testing.assert_close(out.advantages, ref_broadcast(scores, inputs.response_mask))


def test_grpo_all_equal_rewards_give_zero_advantage():
    mask = torch.ones(6, 3, dtype=torch.float64)
    rewards = torch.tensor([1.0, 1.0, 1.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    out = grpo(TokenAdvantageInputs(rewards, mask, group_size=3))
    assert torch.equal(out.advantages[:3], torch.zeros(3, 3, dtype=torch.float64))
    # second group [0, 1, 0]: mean 1/3, unbiased std sqrt(1/3)
    std = math.sqrt(1 / 3)
    expected = torch.tensor([-1 / 3, 2 / 3, -1 / 3], dtype=torch.float64) / (std + 1e-6)
    torch.testing.assert_close(out.advantages[3:, 0], expected)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("estimator", ["grpo", "rloo", "reinforce_pp_baseline"])
def test_constant_groups_are_exactly_zero_despite_rounding(dtype, estimator):
    """7 x 0.1 sums to 0.7000000x in float32; a naive mean would leave ~1e-8 / eps = 0.01."""
    rewards = torch.tensor([0.1] * 7 + [0.3, 0.7] * 7 + [0.7] * 7, dtype=dtype)
    mask = torch.ones(28, 2, dtype=dtype)
    out = compute_advantages(estimator, TokenAdvantageInputs(rewards, mask, group_size=7))
    if estimator == "reinforce_pp_baseline":  # whitening shifts zeros; compare the returns
        assert torch.equal(out.returns[:7], torch.zeros(7, 2, dtype=dtype))
        assert torch.equal(out.returns[21:], torch.zeros(7, 2, dtype=dtype))
    else:
        assert torch.equal(out.advantages[:7], torch.zeros(7, 2, dtype=dtype))
        assert torch.equal(out.advantages[21:], torch.zeros(7, 2, dtype=dtype))
    assert out.advantages[7:21].abs().sum() > 0


def test_grpo_integer_rewards_are_accepted():
    out = grpo(TokenAdvantageInputs(torch.tensor([1, 0, 1, 1]), torch.ones(4, 2), group_size=2))
    assert out.advantages.is_floating_point()
    assert torch.equal(out.advantages[2:], torch.zeros(2, 2))
    assert out.advantages[0, 0] > 0 > out.advantages[1, 0]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("estimator", ["grpo", "dr_grpo", "rloo", "reinforce_pp_baseline"])
def test_explicit_group_ids_equal_consecutive_groups_after_shuffling(
    response_mask_factory, seed, estimator
):
    inputs = random_inputs(response_mask_factory, seed)
    consecutive = compute_advantages(estimator, inputs).advantages
    perm = torch.randperm(8, generator=torch.Generator().manual_seed(100 + seed))
    labels = torch.tensor([10, 10, 10, 10, -3, -3, -3, -3])[perm]  # arbitrary, unsorted labels
    shuffled = TokenAdvantageInputs(
        rewards=inputs.rewards[perm], response_mask=inputs.response_mask[perm],
        token_rewards=inputs.token_rewards[perm], group_ids=labels,
    )
    got = compute_advantages(estimator, shuffled).advantages
    torch.testing.assert_close(got, consecutive[perm])


def test_uneven_explicit_groups_including_a_singleton():
    rewards = torch.tensor([1.0, 3.0, 5.0, 2.0, 7.0], dtype=torch.float64)
    ids = torch.tensor([0, 0, 0, 1, 2])
    mask = torch.ones(5, 1, dtype=torch.float64)
    out = rloo(TokenAdvantageInputs(rewards, mask, group_ids=ids))
    torch.testing.assert_close(out.advantages[:, 0], torch.tensor(
        ref_rloo_scores(rewards, ids.tolist()), dtype=torch.float64))
    assert out.advantages[4, 0] == 0.0  # a group of one has no baseline
    g = grpo(TokenAdvantageInputs(rewards, mask, group_ids=ids))
    torch.testing.assert_close(g.advantages[:, 0], torch.tensor(
        ref_grpo_scores(rewards, ids.tolist(), 1e-6, True), dtype=torch.float64))


@pytest.mark.parametrize("seed", SEEDS)
def test_rloo_matches_reference(response_mask_factory, seed):
    inputs = random_inputs(response_mask_factory, seed)
    out = rloo(inputs)
    scores = ref_rloo_scores(inputs.rewards, [i // 4 for i in range(8)])
    torch.testing.assert_close(out.advantages, ref_broadcast(scores, inputs.response_mask))


def test_rloo_hand_computed():
    rewards = torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    out = rloo(TokenAdvantageInputs(rewards, torch.ones(4, 1), group_size=4))
    torch.testing.assert_close(
        out.advantages[:, 0], torch.tensor([2 / 3, -2 / 3, -2 / 3, 2 / 3], dtype=torch.float64)
    )


@pytest.mark.parametrize(
    "bad", [dict(), dict(group_size=3), dict(group_size=2, group_ids=torch.zeros(4))]
)
def test_group_estimators_reject_bad_grouping(bad):
    inputs = TokenAdvantageInputs(torch.zeros(4), torch.ones(4, 2), **bad)
    with pytest.raises(ValueError, match="group"):
        grpo(inputs)


# --- REINFORCE++ -------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("gamma", [1.0, 0.9])
def test_reinforce_pp_matches_reference(response_mask_factory, seed, gamma):
    inputs = random_inputs(response_mask_factory, seed)
    out = reinforce_pp(inputs, gamma=gamma, eps=1e-8)
    adv, ret = ref_reinforce_pp(inputs.rewards, inputs.response_mask, inputs.token_rewards, gamma,
                                1e-8)
    torch.testing.assert_close(out.advantages, adv)
    torch.testing.assert_close(out.returns, ret)
    valid = inputs.response_mask.bool()
    assert abs(float(out.advantages[valid].mean())) < 1e-10  # whitened over all valid tokens
    assert abs(float(out.advantages[valid].std(correction=0)) - 1.0) < 1e-6


@pytest.mark.parametrize("seed", SEEDS)
def test_reinforce_pp_baseline_matches_reference(response_mask_factory, seed):
    inputs = random_inputs(response_mask_factory, seed)
    out = compute_advantages("reinforce_pp_baseline", inputs, gamma=0.95)
    labels = [i // 4 for i in range(8)]
    centred = ref_grpo_scores(inputs.rewards, labels, 0.0, norm_by_std=False)
    adv, ret = ref_reinforce_pp(centred, inputs.response_mask, inputs.token_rewards, 0.95, 1e-8)
    torch.testing.assert_close(out.advantages, adv)
    torch.testing.assert_close(out.returns, ret)


def test_reinforce_pp_hand_computed_returns():
    mask = torch.tensor([[0, 1, 1, 1]], dtype=torch.float64)
    token_rewards = torch.tensor([[5.0, -0.1, -0.2, -0.3]], dtype=torch.float64)
    out = reinforce_pp(TokenAdvantageInputs(torch.tensor([1.0], dtype=torch.float64), mask,
                                            token_rewards=token_rewards), gamma=0.5)
    # G3 = 1 - 0.3 = 0.7; G2 = -0.2 + 0.35 = 0.15; G1 = -0.1 + 0.075 = -0.025 (prompt ignored)
    torch.testing.assert_close(out.returns, torch.tensor([[0.0, -0.025, 0.15, 0.7]],
                                                         dtype=torch.float64))


# --- calling convention ------------------------------------------------------------------------


def test_all_token_estimators_registered_and_zero_outside_mask(response_mask_factory):
    inputs = random_inputs(response_mask_factory, 7)
    for name in ["gae", "grpo", "dr_grpo", "rloo", "reinforce_pp", "reinforce_pp_baseline"]:
        out = ADVANTAGES.get(name)(inputs)
        assert out.advantages.shape == inputs.response_mask.shape, name
        outside = inputs.response_mask == 0
        assert torch.all(out.advantages[outside] == 0), name
        assert torch.all(out.returns[outside] == 0), name


def test_token_inputs_validate_shapes():
    with pytest.raises(ValueError, match="rewards must be"):
        TokenAdvantageInputs(rewards=torch.zeros(3, 1), response_mask=torch.ones(3, 4))
    with pytest.raises(ValueError, match="values must be aligned"):
        TokenAdvantageInputs(rewards=torch.zeros(3), response_mask=torch.ones(3, 4),
                             values=torch.zeros(3, 5))


def test_token_estimator_rejects_env_inputs():
    from infinirl.algorithms import EnvAdvantageInputs

    env_inputs = EnvAdvantageInputs(rewards=torch.zeros(3, 2), dones=torch.zeros(3, 2))
    with pytest.raises(TypeError, match="TokenAdvantageInputs"):
        grpo(env_inputs)
