"""pass@k: the stable product form equals the definition (enumerate k-subsets) and exact binomials."""

import itertools
import math
from fractions import Fraction

import pytest

from infinirl.evaluation import mean_pass_at_k, pass_at_k


def brute_force(n: int, c: int, k: int) -> float:
    """Fraction of k-subsets of the n samples (the first c correct) that hold a correct one."""
    subsets = list(itertools.combinations(range(n), k))
    return sum(any(i < c for i in s) for s in subsets) / len(subsets)


@pytest.mark.parametrize("n", range(1, 11))
def test_matches_enumeration_of_subsets(n):
    for c in range(n + 1):
        for k in range(1, n + 1):
            assert pass_at_k(n, c, k) == pytest.approx(brute_force(n, c, k), rel=1e-12, abs=1e-15), (n, c, k)


def test_edge_cases():
    assert pass_at_k(8, 0, 1) == 0.0 and pass_at_k(8, 0, 8) == 0.0  # nothing correct
    assert pass_at_k(8, 8, 1) == 1.0 and pass_at_k(1, 1, 1) == 1.0  # everything correct
    assert pass_at_k(8, 3, 6) == 1.0  # only 5 wrong: any 6 hold a correct one
    assert pass_at_k(8, 1, 8) == 1.0 and pass_at_k(8, 1, 7) == pytest.approx(7 / 8)
    for c in range(9):
        assert pass_at_k(8, c, 1) == pytest.approx(c / 8, abs=1e-15)  # pass@1 = mean correctness


@pytest.mark.parametrize("n,c,k", [(200, 1, 100), (200, 3, 100), (1000, 7, 500), (1000, 990, 5), (64, 1, 1)])
def test_stable_where_binomials_overflow_floats(n, c, k):
    exact = 1 - Fraction(math.comb(n - c, k), math.comb(n, k))
    assert pass_at_k(n, c, k) == pytest.approx(float(exact), rel=1e-12)


def test_mean_over_problems_and_bad_input():
    assert mean_pass_at_k([4, 4, 4], [0, 2, 4], 2) == pytest.approx((0 + (1 - 1 / 6) + 1) / 3)
    assert math.isnan(mean_pass_at_k([], [], 1))
    with pytest.raises(ValueError, match="k=5, n=4"):
        pass_at_k(4, 1, 5)
    with pytest.raises(ValueError, match="c=5, n=4"):
        pass_at_k(4, 5, 1)
    with pytest.raises(ValueError, match="k=0"):
        pass_at_k(4, 1, 0)
    with pytest.raises(TypeError, match="k must be an integer"):
        pass_at_k(4, 1, 1.5)
    with pytest.raises(ValueError, match="2 sample counts but 1"):
        mean_pass_at_k([4, 4], [1], 1)
