"""Policy, value and entropy losses: float64 loop references and exact hand-made cases."""

import math

import pytest
import torch

from infinirl.algorithms import (
    POLICY_LOSSES,
    behaviour_importance_weight,
    entropy_from_logits,
    entropy_loss,
    policy_gradient_loss,
    ppo_clip_loss,
    truncated_importance_weight,
    value_loss,
)

SEEDS = [0, 1, 2]
F64 = torch.float64


def ref_ppo(logp, old, adv, mask, clip_low, clip_high, clip_c=None, behaviour=None, cap=None,
            cap_mode="truncate"):
    out = torch.zeros(logp.shape, dtype=F64)
    for i in range(logp.shape[0]):
        for t in range(logp.shape[1]):
            if not mask[i, t]:
                continue
            a = float(adv[i, t])
            ratio = math.exp(float(logp[i, t]) - float(old[i, t]))
            clipped_ratio = min(max(ratio, 1 - clip_low), 1 + clip_high)
            loss = max(-a * ratio, -a * clipped_ratio)
            if clip_c is not None and a < 0:
                loss = min(loss, -a * clip_c)
            if behaviour is not None:
                w = math.exp(float(old[i, t]) - float(behaviour[i, t]))
                if cap is not None:
                    w = min(w, cap) if cap_mode == "truncate" else (0.0 if w > cap else w)
                loss *= w
            out[i, t] = loss
    return out


def random_policy_batch(factory, seed, batch=6, width=9):
    gen = torch.Generator().manual_seed(seed)
    mask = factory(gen, batch, width, empty_rows=1)
    old = -torch.rand(batch, width, generator=gen, dtype=F64) * 3
    logp = old + 0.4 * torch.randn(batch, width, generator=gen, dtype=F64)
    behaviour = old + 0.3 * torch.randn(batch, width, generator=gen, dtype=F64)
    adv = torch.randn(batch, width, generator=gen, dtype=F64)
    return logp, old, behaviour, adv, mask


# --- PPO clip ----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize(
    "clip_low,clip_high,clip_c", [(0.2, None, None), (0.2, 0.28, None), (0.1, 0.3, 3.0)]
)
def test_ppo_clip_matches_reference(response_mask_factory, seed, clip_low, clip_high, clip_c):
    logp, old, _, adv, mask = random_policy_batch(response_mask_factory, seed)
    out = POLICY_LOSSES.get("ppo_clip")(
        logprobs=logp, old_logprobs=old, advantages=adv, response_mask=mask,
        clip_low=clip_low, clip_high=clip_high, clip_c=clip_c,
    )
    high = clip_low if clip_high is None else clip_high
    torch.testing.assert_close(out.loss_mat, ref_ppo(logp, old, adv, mask, clip_low, high, clip_c))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("cap_mode", ["truncate", "mask"])
def test_ppo_with_behaviour_correction_matches_reference(response_mask_factory, seed, cap_mode):
    logp, old, behaviour, adv, mask = random_policy_batch(response_mask_factory, seed)
    out = ppo_clip_loss(
        logprobs=logp, old_logprobs=old, advantages=adv, response_mask=mask, clip_high=0.28,
        behaviour_logprobs=behaviour, is_cap=1.1, is_cap_mode=cap_mode,
    )
    expected = ref_ppo(logp, old, adv, mask, 0.2, 0.28, behaviour=behaviour, cap=1.1,
                       cap_mode=cap_mode)
    torch.testing.assert_close(out.loss_mat, expected)
    for key in ("is_weight_mean", "is_capped_fraction", "behaviour_logprob_abs_diff"):
        assert key in out.metrics


def hand_case():
    ratios = torch.tensor([[1.5, 0.5, 0.5, 1.5, 5.0, 2.0, 5.0, 1.1]], dtype=F64)
    adv = torch.tensor([[1.0, 1.0, -1.0, -1.0, -1.0, -1.0, 1.0, 2.0]], dtype=F64)
    old = torch.full_like(ratios, -1.0)
    logp = (old + ratios.log()).requires_grad_(True)
    return logp, old, adv, torch.ones_like(ratios)


def test_clip_higher_exact_values_and_gradients():
    logp, old, adv, mask = hand_case()
    out = ppo_clip_loss(logprobs=logp, old_logprobs=old, advantages=adv, response_mask=mask,
                        clip_low=0.2, clip_high=0.28)
    # A>0 clipped above at 1.28; A<0 clipped below at 0.8; the pessimistic (max) branch is kept.
    expected = torch.tensor([[-1.28, -0.5, 0.8, 1.5, 5.0, 2.0, -1.28, -2.2]], dtype=F64)
    torch.testing.assert_close(out.loss_mat, expected)
    out.loss_mat.sum().backward()
    # clipped tokens (0, 2, 6) get no gradient; others get d(-A r)/dlogp = -A r
    expected_grad = torch.tensor([[0.0, -0.5, 0.0, 1.5, 5.0, 2.0, 0.0, -2.2]], dtype=F64)
    torch.testing.assert_close(logp.grad, expected_grad)
    torch.testing.assert_close(out.metrics["clip_fraction"], torch.tensor(3 / 8, dtype=F64))
    torch.testing.assert_close(out.metrics["ratio_max"], torch.tensor(5.0, dtype=F64))
    torch.testing.assert_close(out.metrics["ratio_min"], torch.tensor(0.5, dtype=F64))


def test_symmetric_clip_differs_from_clip_higher_only_above():
    logp, old, adv, mask = hand_case()
    out = ppo_clip_loss(logprobs=logp, old_logprobs=old, advantages=adv, response_mask=mask,
                        clip_low=0.2)
    expected = torch.tensor([[-1.2, -0.5, 0.8, 1.5, 5.0, 2.0, -1.2, -2.2]], dtype=F64)
    torch.testing.assert_close(out.loss_mat, expected)


def test_dual_clip_exact_values_and_gradients():
    logp, old, adv, mask = hand_case()
    out = ppo_clip_loss(logprobs=logp, old_logprobs=old, advantages=adv, response_mask=mask,
                        clip_low=0.2, clip_high=0.28, clip_c=3.0)
    # only token 4 (A<0, ratio 5: loss 5 > 3 = -c*A) is bounded; token 6 (A>0, ratio 5) is not.
    expected = torch.tensor([[-1.28, -0.5, 0.8, 1.5, 3.0, 2.0, -1.28, -2.2]], dtype=F64)
    torch.testing.assert_close(out.loss_mat, expected)
    out.loss_mat.sum().backward()
    assert logp.grad[0, 4] == 0.0  # the dual-clip bound is constant in theta
    assert logp.grad[0, 5] == 2.0
    torch.testing.assert_close(out.metrics["dual_clip_fraction"], torch.tensor(1 / 8, dtype=F64))


def test_ppo_rejects_bad_hyperparameters():
    logp, old, adv, mask = hand_case()
    kwargs = dict(logprobs=logp, old_logprobs=old, advantages=adv, response_mask=mask)
    with pytest.raises(ValueError, match="clip_c must be > 1"):
        ppo_clip_loss(**kwargs, clip_c=0.9)
    with pytest.raises(ValueError, match="clip_low"):
        ppo_clip_loss(**kwargs, clip_low=1.5)
    with pytest.raises(ValueError, match="share one shape"):
        ppo_clip_loss(**{**kwargs, "advantages": adv[:, :3]})
    with pytest.raises(ValueError, match="needs behaviour_logprobs"):
        ppo_clip_loss(**kwargs, is_cap=2.0)
    with pytest.raises(ValueError, match="is_cap_mode"):
        ppo_clip_loss(**kwargs, behaviour_logprobs=old, is_cap=2.0, is_cap_mode="clip")


def test_ppo_masked_positions_are_zero_even_if_inputs_are_garbage():
    logp = torch.tensor([[float("nan"), -1.0, 100.0]], dtype=F64, requires_grad=True)
    old = torch.tensor([[0.0, -1.0, -100.0]], dtype=F64)
    adv = torch.tensor([[1.0, 1.0, 1.0]], dtype=F64)
    mask = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    out = ppo_clip_loss(logprobs=logp, old_logprobs=old, advantages=adv, response_mask=mask)
    out.loss_mat.sum().backward()
    assert torch.equal(out.loss_mat, torch.tensor([[0.0, -1.0, 0.0]], dtype=F64))
    assert torch.isfinite(logp.grad).all()


@pytest.mark.parametrize("name", ["ppo_clip", "policy_gradient"])
@pytest.mark.parametrize("garbage", ["advantages", "behaviour_logprobs"])
def test_a_nan_multiplier_at_a_masked_position_leaves_the_gradient_finite(name, garbage):
    """A NaN advantage or behaviour log-prob where the mask is 0 (padding, a dropped decision) must
    not reach the gradient as 0 * NaN: the loss and the gradient equal those of a clean copy."""
    logp = torch.tensor([[-1.0, -0.5, -2.0]], dtype=F64, requires_grad=True)
    inputs = {"old_logprobs": torch.tensor([[-1.2, -0.4, -2.0]], dtype=F64),
              "advantages": torch.tensor([[1.5, -0.7, 0.3]], dtype=F64),
              "behaviour_logprobs": torch.tensor([[-1.1, -0.6, -1.9]], dtype=F64)}
    mask = torch.tensor([[1.0, 1.0, 0.0]], dtype=F64)
    results = []
    for poisoned in (False, True):
        given = dict(inputs)
        if poisoned:
            given[garbage] = given[garbage].clone()
            given[garbage][0, 2] = float("nan")
        logp.grad = None
        out = POLICY_LOSSES.get(name)(logprobs=logp, response_mask=mask, is_cap=2.0, **given)
        out.loss_mat.sum().backward()
        results.append((out.loss_mat.detach(), logp.grad.clone()))
    (clean_loss, clean_grad), (loss, grad) = results
    assert torch.isfinite(grad).all() and torch.equal(grad, clean_grad)
    assert torch.equal(loss, clean_loss)


def test_a_nan_target_at_a_masked_position_leaves_the_value_gradient_finite():
    values = torch.tensor([[0.5, 1.0, 2.0]], dtype=F64, requires_grad=True)
    nan = float("nan")
    out = value_loss(values=values, old_values=torch.tensor([[0.4, nan, 1.0]], dtype=F64),
                     returns=torch.tensor([[1.0, nan, nan]], dtype=F64),
                     response_mask=torch.tensor([[1.0, 0.0, 0.0]]), clip_range=0.2)
    out.loss_mat.sum().backward()
    torch.testing.assert_close(values.grad, torch.tensor([[-0.5, 0.0, 0.0]], dtype=F64))


def test_on_policy_ppo_metrics_are_trivial():
    gen = torch.Generator().manual_seed(0)
    logp = torch.randn(3, 4, generator=gen, dtype=F64)
    out = ppo_clip_loss(logprobs=logp, old_logprobs=logp.clone(), advantages=torch.ones_like(logp),
                        response_mask=torch.ones_like(logp))
    assert out.metrics["approx_kl"] == 0 and out.metrics["clip_fraction"] == 0
    assert out.metrics["ratio_mean"] == 1


# --- importance weights ------------------------------------------------------------------------


def test_truncated_importance_weight_exact_and_detached():
    old = torch.tensor([0.0, -1.0, -2.0], dtype=F64, requires_grad=True)
    behaviour = torch.tensor([-1.0, -1.0, 0.0], dtype=F64)
    weight = truncated_importance_weight(old, behaviour, cap=2.0)
    torch.testing.assert_close(weight, torch.tensor([2.0, 1.0, math.exp(-2.0)], dtype=F64))
    assert not weight.requires_grad


def test_behaviour_weight_mask_mode_drops_tokens_over_cap():
    old = torch.tensor([[0.0, -1.0, -2.0]], dtype=F64)
    behaviour = torch.tensor([[-1.0, -1.0, 0.0]], dtype=F64)
    weight, metrics = behaviour_importance_weight(old, behaviour, torch.ones(1, 3), cap=2.0,
                                                  cap_mode="mask")
    torch.testing.assert_close(weight, torch.tensor([[0.0, 1.0, math.exp(-2.0)]], dtype=F64))
    torch.testing.assert_close(metrics["is_capped_fraction"], torch.tensor(1 / 3, dtype=F64))
    torch.testing.assert_close(metrics["behaviour_logprob_abs_diff"], torch.tensor(1.0, dtype=F64))


def test_tis_weight_gets_no_gradient_but_scales_policy_gradient():
    logp = torch.tensor([[-1.0, -1.0]], dtype=F64, requires_grad=True)
    old = torch.tensor([[-1.0, -1.0]], dtype=F64, requires_grad=True)
    behaviour = torch.tensor([[-1.0 - math.log(3.0), -1.0 + math.log(2.0)]], dtype=F64)
    adv = torch.tensor([[1.0, 1.0]], dtype=F64)
    out = ppo_clip_loss(logprobs=logp, old_logprobs=old, advantages=adv,
                        response_mask=torch.ones(1, 2), behaviour_logprobs=behaviour, is_cap=2.0)
    out.loss_mat.sum().backward()
    # weights: min(3, 2) = 2 and 0.5; on-policy gradient of -A r is -A, scaled by the weight
    torch.testing.assert_close(logp.grad, torch.tensor([[-2.0, -0.5]], dtype=F64))
    assert old.grad is None or torch.all(old.grad == 0)


# --- plain policy gradient ---------------------------------------------------------------------


def test_policy_gradient_on_policy_gradient_is_reinforce():
    gen = torch.Generator().manual_seed(3)
    logp = torch.randn(2, 5, generator=gen, dtype=F64).requires_grad_(True)
    adv = torch.randn(2, 5, generator=gen, dtype=F64)
    mask = torch.tensor([[0, 1, 1, 1, 0], [0, 0, 1, 1, 1]], dtype=F64)
    out = policy_gradient_loss(logprobs=logp, old_logprobs=logp.detach(), advantages=adv,
                               response_mask=mask)
    out.loss_mat.sum().backward()
    torch.testing.assert_close(logp.grad, -adv * mask)
    torch.testing.assert_close(out.loss_mat, -adv * mask)


# --- entropy -----------------------------------------------------------------------------------


def ref_entropy(logits_row):
    peak = max(logits_row)
    weights = [math.exp(z - peak) for z in logits_row]
    total = sum(weights)
    return -sum(w / total * math.log(w / total) for w in weights if w > 0)


@pytest.mark.parametrize("seed", SEEDS)
def test_entropy_from_logits_matches_reference(seed):
    gen = torch.Generator().manual_seed(seed)
    logits = torch.randn(3, 4, 7, generator=gen, dtype=F64) * 5
    expected = torch.tensor([[ref_entropy(logits[i, t].tolist()) for t in range(4)]
                             for i in range(3)], dtype=F64)
    torch.testing.assert_close(entropy_from_logits(logits), expected)


def test_entropy_from_logits_extremes():
    uniform = torch.zeros(1, 8, dtype=F64)
    torch.testing.assert_close(entropy_from_logits(uniform), torch.tensor([math.log(8)], dtype=F64))
    peaked = torch.tensor([[1e4, 0.0, -1e4]], dtype=torch.float32)
    value = entropy_from_logits(peaked)
    assert torch.isfinite(value).all() and abs(float(value)) < 1e-6


def test_entropy_loss_from_logits_or_entropy():
    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 3, 5, generator=gen, dtype=F64)
    mask = torch.tensor([[0, 1, 1], [0, 0, 1]], dtype=F64)
    from_logits = entropy_loss(mask, logits=logits)
    from_entropy = entropy_loss(mask, entropy=entropy_from_logits(logits))
    torch.testing.assert_close(from_logits.loss_mat, -entropy_from_logits(logits) * mask)
    torch.testing.assert_close(from_entropy.loss_mat, from_logits.loss_mat)
    with pytest.raises(ValueError, match="exactly one"):
        entropy_loss(mask)


# --- value loss --------------------------------------------------------------------------------


def ref_value_loss(values, old, returns, mask, clip):
    out = torch.zeros(values.shape, dtype=F64)
    for i in range(values.shape[0]):
        for t in range(values.shape[1]):
            if mask[i, t]:
                v, o, r = float(values[i, t]), float(old[i, t]), float(returns[i, t])
                loss = (v - r) ** 2
                if clip is not None:
                    clipped = o + min(max(v - o, -clip), clip)
                    loss = max(loss, (clipped - r) ** 2)
                out[i, t] = 0.5 * loss
    return out


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("clip", [None, 0.2])
def test_value_loss_matches_reference(response_mask_factory, seed, clip):
    gen = torch.Generator().manual_seed(seed)
    mask = response_mask_factory(gen, 5, 7)
    values, old, returns = (torch.randn(5, 7, generator=gen, dtype=F64) for _ in range(3))
    out = value_loss(values=values, old_values=old, returns=returns, response_mask=mask,
                     clip_range=clip)
    torch.testing.assert_close(out.loss_mat, ref_value_loss(values, old, returns, mask, clip))


def test_value_loss_clipping_exact():
    values = torch.tensor([[2.0, 0.0, 1.8]], dtype=F64, requires_grad=True)
    old = torch.tensor([[1.0, 1.0, 1.0]], dtype=F64)
    returns = torch.tensor([[0.0, 2.0, 2.0]], dtype=F64)
    out = value_loss(values=values, old_values=old, returns=returns,
                     response_mask=torch.ones(1, 3), clip_range=0.5)
    torch.testing.assert_close(out.loss_mat, torch.tensor([[2.0, 2.0, 0.125]], dtype=F64))
    out.loss_mat.sum().backward()
    # 0.5 factor: gradient is the plain error V - R; the third value is clipped (constant branch)
    torch.testing.assert_close(values.grad, torch.tensor([[2.0, -2.0, 0.0]], dtype=F64))
    torch.testing.assert_close(out.metrics["value_clip_fraction"], torch.tensor(1 / 3, dtype=F64))
