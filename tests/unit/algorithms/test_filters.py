"""DAPO dynamic sampling and overlong reward shaping."""

import pytest
import torch
from tensordict import TensorDict

from infinirl.algorithms import (
    DynamicSamplingBuffer,
    group_is_informative,
    overlong_penalty,
)


def ref_informative(rewards, group_size, atol):
    flags = []
    for start in range(0, len(rewards), group_size):
        group = rewards[start : start + group_size]
        flags.append(max(group) - min(group) > atol)
    return flags


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_group_is_informative_matches_reference(seed):
    gen = torch.Generator().manual_seed(seed)
    rewards = torch.randint(0, 2, (24,), generator=gen).to(torch.float64)
    rewards[:4] = 1.0  # at least one all-equal group
    got = group_is_informative(rewards, 4)
    assert got.tolist() == ref_informative(rewards.tolist(), 4, 1e-6)
    assert not got[0]


def test_group_is_informative_tolerance_and_errors():
    rewards = torch.tensor([0.5, 0.5 + 1e-9, 0.2, 0.3])
    assert group_is_informative(rewards, 2).tolist() == [False, True]
    assert group_is_informative(rewards, 2, atol=0.2).tolist() == [False, False]
    with pytest.raises(ValueError, match="divide"):
        group_is_informative(rewards, 3)


def round_of(start_id, rewards):
    """One generation round: sample ids (to check what was kept) and their rewards."""
    rewards = torch.tensor(rewards, dtype=torch.float64)
    ids = torch.arange(start_id, start_id + len(rewards))
    return TensorDict({"id": ids, "reward": rewards}, batch_size=[len(rewards)]), rewards


def test_buffer_fills_across_rounds_and_truncates_to_target():
    buffer = DynamicSamplingBuffer(target_groups=3, max_extra_rounds=5, group_size=2)
    assert buffer.needs_more()
    # round 1: groups (1,1) dropped, (0,1) kept, (0,0) dropped
    assert buffer.add(*round_of(0, [1, 1, 0, 1, 0, 0])) == 1
    assert buffer.needs_more() and not buffer.is_full
    # round 2: (1,0) kept, (1,1) dropped, (0,1) kept -> 3 groups: full
    assert buffer.add(*round_of(100, [1, 0, 1, 1, 0, 1])) == 2
    assert buffer.is_full and not buffer.needs_more() and not buffer.cap_reached
    with pytest.raises(RuntimeError, match="take"):
        buffer.add(*round_of(200, [0, 1]))
    result = buffer.take()
    assert result.samples["id"].tolist() == [2, 3, 100, 101, 104, 105]
    assert result.num_groups == 3 and not result.cap_reached
    assert result.metrics == {"groups_seen": 6.0, "groups_kept": 3.0, "groups_dropped": 3.0,
                              "groups_surplus": 0.0, "rounds": 2.0}
    assert buffer.needs_more() and buffer.rounds == 0  # take() resets for the next step


def test_buffer_discards_surplus_groups_beyond_target():
    buffer = DynamicSamplingBuffer(target_groups=1, max_extra_rounds=0, group_size=2)
    buffer.add(*round_of(0, [0, 1, 1, 0]))
    result = buffer.take()
    assert result.samples["id"].tolist() == [0, 1]
    assert result.metrics["groups_surplus"] == 1.0


def test_buffer_cap_reached_returns_partial_batch_with_flag():
    buffer = DynamicSamplingBuffer(target_groups=4, max_extra_rounds=1, group_size=2)
    buffer.add(*round_of(0, [0, 1, 1, 1]))
    assert buffer.needs_more()
    buffer.add(*round_of(10, [0, 0, 1, 1]))  # the one extra round: nothing informative
    assert buffer.cap_reached and not buffer.needs_more()
    result = buffer.take()
    assert result.cap_reached and result.num_groups == 1
    assert result.samples["id"].tolist() == [0, 1]
    assert result.metrics["rounds"] == 2.0 and result.metrics["groups_dropped"] == 3.0


def test_buffer_with_nothing_informative_returns_none_and_works_with_plain_tensors():
    buffer = DynamicSamplingBuffer(target_groups=1, max_extra_rounds=0, group_size=2)
    buffer.add(torch.arange(4), torch.tensor([1.0, 1.0, 0.0, 0.0]))
    result = buffer.take()
    assert result.samples is None and result.cap_reached and result.num_groups == 0
    buffer.add(torch.arange(4), torch.tensor([1.0, 1.0, 0.0, 1.0]))
    assert torch.equal(buffer.take().samples, torch.tensor([2, 3]))


def test_buffer_rejects_bad_configuration():
    with pytest.raises(ValueError, match="max_extra_rounds"):
        DynamicSamplingBuffer(target_groups=1, max_extra_rounds=-1, group_size=2)


# --- overlong shaping --------------------------------------------------------------------------


def ref_overlong(length, max_len, buffer, factor):
    if length <= max_len - buffer:
        return 0.0
    if length <= max_len:
        return factor * ((max_len - buffer) - length) / buffer
    return -factor


def test_overlong_penalty_exact_values_at_boundaries():
    lengths = torch.tensor([0, 12, 16, 17, 18, 20, 21, 100])
    got = overlong_penalty(lengths, max_response_length=20, buffer_length=4, penalty_factor=1.0)
    expected = [0.0, 0.0, 0.0, -0.25, -0.5, -1.0, -1.0, -1.0]
    assert got.tolist() == expected


@pytest.mark.parametrize("factor", [1.0, 0.5])
def test_overlong_penalty_matches_reference(factor):
    lengths = torch.arange(0, 40, dtype=torch.float64)
    got = overlong_penalty(lengths, max_response_length=30, buffer_length=7, penalty_factor=factor)
    expected = [ref_overlong(n, 30, 7, factor) for n in range(40)]
    torch.testing.assert_close(got, torch.tensor(expected, dtype=torch.float64))


def test_overlong_penalty_rejects_bad_buffer():
    with pytest.raises(ValueError, match="buffer_length"):
        overlong_penalty(torch.tensor([1]), max_response_length=10, buffer_length=0)
    with pytest.raises(ValueError, match="buffer_length"):
        overlong_penalty(torch.tensor([1]), max_response_length=10, buffer_length=11)
