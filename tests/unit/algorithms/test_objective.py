"""The actor's objective wires the off-policy correction through, split-invariantly."""

import pytest

from infinirl.algorithms.objective import PolicyObjectiveConfig, policy_objective
from tests.unit.algorithms.test_losses import random_policy_batch, ref_ppo


class MicroBatch(dict):
    def keys(self):  # what policy_objective reads, as on a TensorDict
        return list(super().keys())


@pytest.mark.parametrize("cap_mode", ["truncate", "mask"])
def test_the_behaviour_correction_reaches_the_loss_and_splits_invariantly(response_mask_factory, cap_mode):
    logp, old, behaviour, adv, mask = random_policy_batch(response_mask_factory, 4, batch=8)
    cfg = PolicyObjectiveConfig(clip_low=0.2, clip_high=0.28, is_cap=1.1, is_cap_mode=cap_mode)
    normaliser = float(mask.sum())  # token-mean over the whole mini-batch

    def loss_of(rows):
        micro = MicroBatch(response_mask=mask[rows], old_logprobs=old[rows], advantages=adv[rows],
                           rollout_logprobs=behaviour[rows])
        return policy_objective(micro, logp[rows], None, cfg, normaliser)

    whole, metrics = loss_of(slice(None))
    expected = ref_ppo(logp, old, adv, mask, 0.2, 0.28, behaviour=behaviour, cap=1.1, cap_mode=cap_mode).sum()
    assert float(whole) == pytest.approx(float(expected) / normaliser, rel=1e-12)
    halves = float(loss_of(slice(0, 4))[0]) + float(loss_of(slice(4, 8))[0])
    assert halves == pytest.approx(float(whole), rel=1e-12)
    assert "train/is_capped_fraction" in metrics


def test_without_a_cap_the_rollout_logprobs_only_feed_the_mismatch_metric(response_mask_factory):
    logp, old, behaviour, adv, mask = random_policy_batch(response_mask_factory, 1)
    micro = MicroBatch(response_mask=mask, old_logprobs=old, advantages=adv, rollout_logprobs=behaviour)
    loss, metrics = policy_objective(micro, logp, None, PolicyObjectiveConfig(), float(mask.sum()))
    expected = ref_ppo(logp, old, adv, mask, 0.2, 0.2).sum() / mask.sum()
    assert float(loss) == pytest.approx(float(expected), rel=1e-12)
    assert "train/is_weight_mean" not in metrics and "train/logprob_mismatch_mean" in metrics


def reference_mismatch(trainer, rollout, mask):
    """Mean and max of |trainer - rollout| over the masked tokens, in float64 loops."""
    gaps = [abs(float(trainer[i, t]) - float(rollout[i, t]))
            for i in range(mask.shape[0]) for t in range(mask.shape[1]) if mask[i, t]]
    return sum(gaps) / len(gaps), max(gaps)


@pytest.mark.parametrize("with_old", [True, False])
def test_the_mismatch_metric_compares_the_rollout_with_the_trainer_before_the_update(response_mask_factory,
                                                                                      with_old):
    """Against ``old_logprobs`` (the trainer's before the update), not the current log-probs: after
    the first mini-batch those hold the policy's own drift. Without ``old_logprobs`` (one on-policy
    update) the current log-probs are the trainer's before the update."""
    logp, old, behaviour, adv, mask = random_policy_batch(response_mask_factory, 2)
    micro = MicroBatch(response_mask=mask, advantages=adv, rollout_logprobs=behaviour)
    if with_old:
        micro["old_logprobs"] = old
    _, metrics = policy_objective(micro, logp, None, PolicyObjectiveConfig(), float(mask.sum()))
    mean, largest = reference_mismatch(old if with_old else logp, behaviour, mask)
    assert metrics["train/logprob_mismatch_mean"] == pytest.approx(mean, rel=1e-12)
    assert metrics["train/logprob_mismatch_max"] == pytest.approx(largest, rel=1e-12)
