"""Per-token estimators of KL(pi || pi_ref) from sampled tokens, and their two uses.

With tokens sampled from the current policy ``pi`` and ``log_r = log pi_ref(x) - log pi(x)``,
J. Schulman's note "Approximating KL Divergence" (2020) gives three unbiased-or-nearly estimators of
``KL(pi || pi_ref)``:

* ``k1 = -log_r``                    unbiased, high variance, can be negative;
* ``k2 = 0.5 * log_r**2``            biased, low variance, always >= 0;
* ``k3 = (exp(log_r) - 1) - log_r``  unbiased, low variance, always >= 0 (the usual GRPO choice).

Two ways to use them, both per token in the ``[B, L]`` layout:

* as a **loss term** (GRPO-style): :func:`kl_loss` gives a per-token loss matrix to aggregate like
  the policy loss (``aggregation.aggregate``), scaled by a coefficient and differentiated;
* as a **reward penalty** (InstructGPT/PPO-style): :func:`kl_penalty` gives detached per-token
  rewards ``-coef * kl`` for ``TokenAdvantageInputs.token_rewards``.
"""

from __future__ import annotations

import torch

from infinirl.algorithms.masking import zero_outside
from infinirl.algorithms.registry import KL_ESTIMATORS

__all__ = ["k1", "k2", "k3", "kl_loss", "kl_penalty"]


@KL_ESTIMATORS.register("k1")
def k1(logprobs: torch.Tensor, ref_logprobs: torch.Tensor) -> torch.Tensor:
    """``log pi - log pi_ref``: the plain log-ratio."""
    return logprobs - ref_logprobs


@KL_ESTIMATORS.register("k2")
def k2(logprobs: torch.Tensor, ref_logprobs: torch.Tensor) -> torch.Tensor:
    """``0.5 * (log pi - log pi_ref)**2``."""
    return 0.5 * (logprobs - ref_logprobs) ** 2


@KL_ESTIMATORS.register("k3")
def k3(logprobs: torch.Tensor, ref_logprobs: torch.Tensor) -> torch.Tensor:
    """``pi_ref/pi - 1 - log(pi_ref/pi)``. The log-ratio is clamped above at 20 before ``exp``, so
    a token the reference finds far likelier cannot overflow to inf. It is not clamped below (verl
    clamps at -20 too): there ``exp`` only underflows to 0, and a clamp would report ~19 and cut
    the gradient (~1) of a token the policy finds far likelier than the reference does."""
    log_ratio = (ref_logprobs - logprobs).clamp(max=20.0)
    return torch.expm1(log_ratio) - log_ratio


def kl_loss(
    logprobs: torch.Tensor,
    ref_logprobs: torch.Tensor,
    response_mask: torch.Tensor,
    estimator: str = "k3",
) -> torch.Tensor:
    """Per-token KL loss matrix (0 outside ``response_mask``), differentiable in ``logprobs``.

    Multiply by the KL coefficient and aggregate with the same mode and normaliser as the policy
    loss, so the whole objective stays micro-batch invariant.
    """
    kl = KL_ESTIMATORS.get(estimator)(logprobs, ref_logprobs.detach())
    return zero_outside(kl, response_mask)


def kl_penalty(
    logprobs: torch.Tensor,
    ref_logprobs: torch.Tensor,
    response_mask: torch.Tensor,
    coef: float,
    estimator: str = "k1",
) -> torch.Tensor:
    """Per-token rewards ``-coef * KL`` (detached, 0 outside ``response_mask``).

    Feed the result to ``TokenAdvantageInputs.token_rewards``; the advantage estimator then folds
    it into returns (Ouyang et al. 2022, eq. 2, uses ``k1`` per token).
    """
    with torch.no_grad():
        kl = KL_ESTIMATORS.get(estimator)(logprobs, ref_logprobs)
        return zero_outside(-coef * kl, response_mask)
