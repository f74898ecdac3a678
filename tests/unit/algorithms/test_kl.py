"""KL estimators k1/k2/k3: formulas, Monte Carlo unbiasedness, loss and reward-penalty uses."""

import math

import pytest
import torch

from infinirl.algorithms import KL_ESTIMATORS, kl_loss, kl_penalty

F64 = torch.float64


def ref_estimator(name, logp, ref):
    log_r = ref - logp  # log(pi_ref / pi)
    return {"k1": -log_r, "k2": 0.5 * log_r**2, "k3": math.exp(log_r) - 1 - log_r}[name]


@pytest.mark.parametrize("name", ["k1", "k2", "k3"])
@pytest.mark.parametrize("seed", [0, 1])
def test_estimators_match_formulas(name, seed):
    gen = torch.Generator().manual_seed(seed)
    logp = -torch.rand(4, 6, generator=gen, dtype=F64) * 4
    ref = -torch.rand(4, 6, generator=gen, dtype=F64) * 4
    expected = torch.tensor([[ref_estimator(name, float(logp[i, t]), float(ref[i, t]))
                              for t in range(6)] for i in range(4)], dtype=F64)
    torch.testing.assert_close(KL_ESTIMATORS.get(name)(logp, ref), expected)


def test_k1_and_k3_are_unbiased_estimates_of_kl_and_k2_k3_nonnegative():
    gen = torch.Generator().manual_seed(0)
    pi = torch.softmax(torch.randn(6, generator=gen, dtype=F64), dim=0)
    pi_ref = torch.softmax(torch.randn(6, generator=gen, dtype=F64), dim=0)
    true_kl = float((pi * (pi.log() - pi_ref.log())).sum())
    tokens = torch.multinomial(pi, 200_000, replacement=True, generator=gen)
    logp, ref = pi.log()[tokens], pi_ref.log()[tokens]
    for name in ("k1", "k3"):
        estimate = float(KL_ESTIMATORS.get(name)(logp, ref).mean())
        assert abs(estimate - true_kl) < 0.02 * max(1.0, true_kl), (name, estimate, true_kl)
    assert bool((KL_ESTIMATORS.get("k2")(logp, ref) >= 0).all())
    assert bool((KL_ESTIMATORS.get("k3")(logp, ref) >= 0).all())
    # k3 has lower variance than k1 when the distributions are close (Schulman 2020)
    close_ref = torch.log(0.9 * pi + 0.1 * pi_ref)[tokens]
    k1_var = KL_ESTIMATORS.get("k1")(logp, close_ref).var()
    assert KL_ESTIMATORS.get("k3")(logp, close_ref).var() < k1_var


def test_k3_is_finite_for_extreme_log_ratios():
    logp = torch.tensor([-200.0, 0.0], dtype=torch.float32)
    ref = torch.tensor([0.0, -200.0], dtype=torch.float32)
    assert torch.isfinite(KL_ESTIMATORS.get("k3")(logp, ref)).all()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_k3_keeps_its_gradient_when_the_policy_is_far_likelier_than_the_reference(dtype):
    """log pi = 0, log pi_ref = -30: k3 = e^-30 - 1 + 30 ~ 29 and d k3 / d log pi = 1 - e^-30 ~ 1.
    Only the side of the log-ratio that can overflow exp() may be clamped: a clamp at -20 would
    report ~19 and give no gradient, so the KL term would stop pulling such tokens back."""
    logp = torch.tensor([[0.0, -0.01]], dtype=dtype, requires_grad=True)
    ref = torch.tensor([[-30.0, -25.0]], dtype=dtype)
    kl = kl_loss(logp, ref, torch.ones(1, 2), estimator="k3")
    kl.sum().backward()
    expected = [math.expm1(r - lp) - (r - lp) for lp, r in ((0.0, -30.0), (-0.01, -25.0))]
    torch.testing.assert_close(kl.detach().double(), torch.tensor([expected], dtype=F64), rtol=1e-6, atol=0)
    torch.testing.assert_close(logp.grad.double(), torch.tensor([[1 - math.exp(-30.0), 1 - math.exp(-24.99)]],
                                                                dtype=F64), rtol=1e-6, atol=0)


def test_kl_loss_is_masked_and_differentiable_in_policy_only():
    logp = torch.tensor([[-1.0, -2.0, -0.5]], dtype=F64, requires_grad=True)
    ref = torch.tensor([[-1.5, -1.0, -0.5]], dtype=F64, requires_grad=True)
    mask = torch.tensor([[0.0, 1.0, 1.0]], dtype=F64)
    loss = kl_loss(logp, ref, mask, estimator="k3")
    expected = torch.tensor([[0.0, math.exp(1.0) - 2.0, 0.0]], dtype=F64)
    torch.testing.assert_close(loss, expected)
    loss.sum().backward()
    # d k3 / d logp = 1 - exp(ref - logp)
    torch.testing.assert_close(logp.grad, torch.tensor([[0.0, 1 - math.e, 0.0]], dtype=F64))
    assert ref.grad is None


def test_kl_penalty_is_negative_scaled_detached_and_masked():
    logp = torch.tensor([[-1.0, -2.0, -0.5]], dtype=F64, requires_grad=True)
    ref = torch.tensor([[-1.5, -1.0, -0.75]], dtype=F64)
    mask = torch.tensor([[0.0, 1.0, 1.0]], dtype=F64)
    penalty = kl_penalty(logp, ref, mask, coef=0.1)
    torch.testing.assert_close(penalty, torch.tensor([[0.0, 0.1, -0.025]], dtype=F64))
    assert not penalty.requires_grad


def test_unknown_estimator_lists_names():
    with pytest.raises(KeyError, match="registered: k1, k2, k3"):
        kl_loss(torch.zeros(1, 1), torch.zeros(1, 1), torch.ones(1, 1), estimator="k4")
