"""Masked statistics and group bookkeeping shared by the estimators and losses."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from infinirl.algorithms import group_index, group_stats, masked_mean, masked_whiten, zero_outside
from infinirl.algorithms.masking import last_valid_index, masked_max, masked_min

F64 = torch.float64

row_masks = st.lists(st.lists(st.booleans(), min_size=5, max_size=5), min_size=1, max_size=4)


@settings(max_examples=40, deadline=None)
@given(mask_rows=row_masks, seed=st.integers(0, 1000))
def test_masked_statistics_match_python(mask_rows, seed):
    mask = torch.tensor(mask_rows)
    values = torch.randn(mask.shape, generator=torch.Generator().manual_seed(seed), dtype=F64)
    selected = [float(v) for v, m in zip(values.flatten(), mask.flatten()) if m]
    expected_mean = sum(selected) / len(selected) if selected else 0.0
    assert float(masked_mean(values, mask)) == pytest.approx(expected_mean, abs=1e-12)
    assert float(masked_max(values, mask)) == (max(selected) if selected else 0.0)
    assert float(masked_min(values, mask)) == (min(selected) if selected else 0.0)
    expected_last = [max((t for t, m in enumerate(row) if m), default=-1) for row in mask_rows]
    assert last_valid_index(mask).tolist() == expected_last
    whitened = masked_whiten(values, mask)
    assert torch.all(whitened[~mask] == 0)
    if len(selected) > 1 and max(selected) - min(selected) > 1e-3:
        chosen = whitened[mask]
        assert float(chosen.mean()) == pytest.approx(0.0, abs=1e-9)
        # sqrt(var / (var + eps)), not 1: close values have a variance not far above eps = 1e-8
        variance = sum((v - expected_mean) ** 2 for v in selected) / len(selected)
        assert float(chosen.std(correction=0)) == pytest.approx((variance / (variance + 1e-8)) ** 0.5, rel=1e-9)


def test_zero_outside_blocks_nan_and_its_gradient():
    values = torch.tensor([float("nan"), 2.0, float("inf")], requires_grad=True)
    out = zero_outside(values, torch.tensor([0, 1, 0]))
    out.sum().backward()
    assert out.tolist() == [0.0, 2.0, 0.0] and values.grad.tolist() == [0.0, 1.0, 0.0]


def test_mask_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="mask shape"):
        masked_mean(torch.zeros(2, 3), torch.ones(2, 4))


def test_group_index_and_stats():
    index, groups = group_index(5, group_ids=torch.tensor([9, 4, 9, 4, 1]))
    assert groups == 3 and index.tolist() == [2, 1, 2, 1, 0]
    stats = group_stats(torch.tensor([1.0, 2.0, 3.0, 6.0, 5.0], dtype=F64), index, groups)
    assert stats.count.tolist() == [2, 2, 2, 2, 1]
    assert stats.mean.tolist() == [2.0, 4.0, 2.0, 4.0, 5.0]
    torch.testing.assert_close(stats.std, torch.tensor([2**0.5, 8**0.5, 2**0.5, 8**0.5, 0.0],
                                                       dtype=F64))
    assert group_index(6, group_size=3)[0].tolist() == [0, 0, 0, 1, 1, 1]
    with pytest.raises(ValueError, match="one label per sample"):
        group_index(3, group_ids=torch.zeros(4))
