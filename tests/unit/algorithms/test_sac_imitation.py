"""SAC critic/actor/temperature losses and BC/DAgger losses against loop references."""

import math

import pytest
import torch

from infinirl.algorithms import (
    bc_mse_loss,
    bc_nll_loss,
    sac_actor_loss,
    sac_critic_loss,
    sac_temperature_loss,
    soft_q_target,
)

F64 = torch.float64


def random_transitions(seed, batch=7):
    gen = torch.Generator().manual_seed(seed)
    return {
        "q": torch.randn(2, batch, generator=gen, dtype=F64),
        "next_q": torch.randn(2, batch, generator=gen, dtype=F64),
        "rewards": torch.randn(batch, generator=gen, dtype=F64),
        "terminated": torch.rand(batch, generator=gen) < 0.3,
        "next_logp": -torch.rand(batch, generator=gen, dtype=F64) * 3,
        "logp": -torch.rand(batch, generator=gen, dtype=F64) * 3,
    }


def ref_targets(d, alpha, gamma):
    out = []
    for i in range(d["rewards"].shape[0]):
        min_next = min(float(d["next_q"][0, i]), float(d["next_q"][1, i]))
        soft = min_next - alpha * float(d["next_logp"][i])
        cont = 0.0 if bool(d["terminated"][i]) else 1.0
        out.append(float(d["rewards"][i]) + gamma * cont * soft)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sac_critic_loss_matches_reference(seed):
    d = random_transitions(seed)
    alpha, gamma = 0.2, 0.9
    target = ref_targets(d, alpha, gamma)
    out = sac_critic_loss(q_values=d["q"], rewards=d["rewards"], terminated=d["terminated"],
                          next_target_q_values=d["next_q"], next_logprobs=d["next_logp"],
                          alpha=alpha, gamma=gamma)
    n = len(target)
    expected = sum(sum(0.5 * (float(d["q"][k, i]) - target[i]) ** 2 for i in range(n)) / n
                   for k in range(2))
    assert out.loss.item() == pytest.approx(expected, rel=1e-12)
    torch.testing.assert_close(
        soft_q_target(rewards=d["rewards"], terminated=d["terminated"],
                      next_target_q_values=list(d["next_q"]), next_logprobs=d["next_logp"],
                      alpha=alpha, gamma=gamma),
        torch.tensor(target, dtype=F64),
    )


def test_sac_critic_target_exact_and_gradient_only_through_q():
    q = torch.tensor([[1.0, 0.0], [2.0, 0.0]], dtype=F64, requires_grad=True)
    next_q = torch.tensor([[3.0, 5.0], [4.0, 1.0]], dtype=F64, requires_grad=True)
    alpha = torch.tensor(0.5, dtype=F64, requires_grad=True)
    out = sac_critic_loss(q_values=q, rewards=torch.tensor([1.0, 1.0], dtype=F64),
                          terminated=torch.tensor([False, True]), next_target_q_values=next_q,
                          next_logprobs=torch.tensor([-2.0, -2.0], dtype=F64), alpha=alpha,
                          gamma=0.5)
    # y0 = 1 + 0.5 * (min(3, 4) + 0.5 * 2) = 3;  y1 = 1 (terminated: no bootstrap)
    torch.testing.assert_close(out.metrics["q_target_mean"], torch.tensor(2.0, dtype=F64))
    out.loss.backward()
    # d/dQ_k of sum_k mean_i 0.5 (Q_ki - y_i)^2 = (Q_ki - y_i) / B
    torch.testing.assert_close(q.grad, torch.tensor([[-1.0, -0.5], [-0.5, -0.5]], dtype=F64))
    assert next_q.grad is None and alpha.grad is None


def test_sac_actor_loss_reference_and_alpha_detached():
    d = random_transitions(4)
    alpha = torch.tensor(0.3, dtype=F64, requires_grad=True)
    logp = d["logp"].clone().requires_grad_(True)
    out = sac_actor_loss(logprobs=logp, q_values=d["q"], alpha=alpha)
    n = logp.shape[0]
    expected = sum(0.3 * float(d["logp"][i]) - min(float(d["q"][0, i]), float(d["q"][1, i]))
                   for i in range(n)) / n
    assert out.loss.item() == pytest.approx(expected, rel=1e-12)
    out.loss.backward()
    torch.testing.assert_close(logp.grad, torch.full((n,), 0.3 / n, dtype=F64))
    assert alpha.grad is None


def test_sac_temperature_loss_raises_alpha_when_entropy_too_low():
    log_alpha = torch.tensor(math.log(0.1), dtype=F64, requires_grad=True)
    logp = torch.tensor([1.0, 3.0], dtype=F64, requires_grad=True)  # entropy ~ -2 < target -1
    out = sac_temperature_loss(log_alpha=log_alpha, logprobs=logp, target_entropy=-1.0)
    assert out.loss.item() == pytest.approx(-math.log(0.1) * 1.0)
    out.loss.backward()
    assert log_alpha.grad.item() == pytest.approx(-1.0)  # descent increases log_alpha
    assert logp.grad is None
    torch.testing.assert_close(out.metrics["alpha"], torch.tensor(0.1, dtype=F64))


def test_sac_rejects_wrong_critic_shape():
    with pytest.raises(ValueError, match=r"\[K, B\]"):
        sac_actor_loss(logprobs=torch.zeros(3), q_values=torch.zeros(3), alpha=0.1)


# --- imitation ---------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
def test_bc_mse_matches_reference_with_and_without_sample_mask(seed):
    gen = torch.Generator().manual_seed(seed)
    pred = torch.randn(5, 3, 2, generator=gen, dtype=F64)  # chunks of 3 actions of 2 dims
    expert = torch.randn(5, 3, 2, generator=gen, dtype=F64)
    mask = torch.tensor([1, 0, 1, 1, 0])
    per_sample = [sum((float(pred[i, c, d]) - float(expert[i, c, d])) ** 2
                      for c in range(3) for d in range(2)) / 6 for i in range(5)]
    assert bc_mse_loss(pred, expert).item() == pytest.approx(sum(per_sample) / 5, rel=1e-12)
    kept = [per_sample[i] for i in range(5) if mask[i]]
    assert bc_mse_loss(pred, expert, mask).item() == pytest.approx(sum(kept) / 3, rel=1e-12)
    expected = torch.nn.functional.mse_loss(pred, expert)
    torch.testing.assert_close(bc_mse_loss(pred, expert), expected)


def test_bc_nll_per_token_mask_and_gradient():
    logp = torch.tensor([[-1.0, -2.0, -9.0], [-3.0, -9.0, -9.0]], dtype=F64, requires_grad=True)
    mask = torch.tensor([[1, 1, 0], [1, 0, 0]])
    loss = bc_nll_loss(logp, mask)
    assert loss.item() == pytest.approx(2.0)
    loss.backward()
    torch.testing.assert_close(logp.grad, -mask.to(F64) / 3)
    assert bc_nll_loss(torch.tensor([-1.0, -3.0])).item() == pytest.approx(2.0)


def test_imitation_shape_errors():
    with pytest.raises(ValueError, match="same shape"):
        bc_mse_loss(torch.zeros(2, 3), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="mask must be"):
        bc_nll_loss(torch.zeros(2, 3), torch.ones(3))
