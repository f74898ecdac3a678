"""pass@k from ``n`` samples per problem, ``c`` of them correct: pure functions, no I/O.

The unbiased estimator of Chen et al. (2021, "Evaluating Large Language Models Trained on Code")
is the probability that ``k`` samples drawn without replacement from the ``n`` contain a correct
one: ``1 - C(n - c, k) / C(n, k)``. The binomials overflow floats for realistic ``n`` (C(200, 100)
is ~1e58), so it is computed as the product ``prod_{i = n-c+1}^{n} (1 - k / i)``, which equals the
ratio exactly and whose factors all lie in [0, 1). pass@1 is the mean correctness of the samples.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def pass_at_k(n: int, c: int, k: int) -> float:
    """Probability that at least one of ``k`` of the ``n`` samples (``c`` correct) is correct."""
    for name, value in (("n", n), ("c", c), ("k", k)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise TypeError(f"pass_at_k: {name} must be an integer, got {value!r}")
    if not 0 <= c <= n:
        raise ValueError(f"pass_at_k: need 0 <= c <= n, got c={c}, n={n}")
    if not 1 <= k <= n:
        raise ValueError(f"pass_at_k: need 1 <= k <= n (k samples out of n), got k={k}, n={n}")
    if n - c < k:  # every k-subset holds a correct sample
        return 1.0
    i = np.arange(n - c + 1, n + 1, dtype=np.float64)
    return float(1.0 - np.prod(1.0 - k / i))


def mean_pass_at_k(num_samples: Sequence[int], num_correct: Sequence[int], k: int) -> float:
    """pass@k averaged over problems (``num_samples[i]`` samples, ``num_correct[i]`` correct)."""
    if len(num_samples) != len(num_correct):
        raise ValueError(f"mean_pass_at_k: {len(num_samples)} sample counts but {len(num_correct)} correct counts")
    if not num_samples:
        return float("nan")
    return float(np.mean([pass_at_k(int(n), int(c), k) for n, c in zip(num_samples, num_correct)]))
