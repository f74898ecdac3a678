"""explained_variance against a float64 Python reference over the valid tokens."""

import pytest
import torch

from infinirl.algorithms import explained_variance


def python_reference(values, returns, mask) -> float:
    pairs = [(float(v), float(r)) for v, r, m in zip(values.flatten(), returns.flatten(), mask.flatten()) if m]
    rs = [r for _, r in pairs]
    residuals = [r - v for v, r in pairs]

    def var(xs):
        mean = sum(xs) / len(xs)
        return sum((x - mean) ** 2 for x in xs) / len(xs)

    return 1.0 - var(residuals) / var(rs)


@pytest.mark.parametrize("seed", range(5))
def test_matches_python(seed, response_mask_factory):
    gen = torch.Generator().manual_seed(seed)
    mask = response_mask_factory(gen, 6, 9)
    returns = torch.randn(mask.shape, generator=gen, dtype=torch.float64)
    values = returns + 0.5 * torch.randn(mask.shape, generator=gen, dtype=torch.float64)
    values = torch.where(mask.bool(), values, torch.full_like(values, float("nan")))  # ignored
    got = explained_variance(values, returns, mask)
    assert got.dtype == torch.float64
    assert float(got) == pytest.approx(python_reference(values, returns, mask), abs=1e-12)


def test_edge_cases():
    mask = torch.tensor([[0.0, 1.0, 1.0, 1.0]])
    returns = torch.tensor([[9.0, 1.0, 2.0, 3.0]])
    assert float(explained_variance(returns.clone(), returns, mask)) == pytest.approx(1.0)  # perfect
    assert float(explained_variance(torch.zeros(1, 4), returns, mask)) == pytest.approx(0.0)  # a constant
    assert float(explained_variance(-returns, returns, mask)) < 0  # worse than a constant
    flat = torch.ones(1, 4)
    assert float(explained_variance(torch.zeros(1, 4), flat, mask)) == 0.0  # nothing to explain
