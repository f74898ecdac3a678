"""The actor's objective (``policy_objective``): the off-policy correction wired through, the
mismatch metrics, and the whole objective (PPO + KL + entropy, every aggregation mode, with and
without old log-probs) on a tiny float64 model against a loop reference, split-invariantly."""

import copy
import math

import pytest
import torch

from infinirl.algorithms import aggregation_normaliser
from infinirl.algorithms.objective import PolicyObjectiveConfig, policy_objective
from tests.unit.algorithms.test_aggregation import VOCAB, TinyLM, aligned_logprobs_and_entropy
from tests.unit.algorithms.test_losses import F64, random_policy_batch, ref_ppo


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


# --- the whole objective on a real (tiny) model: float64 loop reference, split-invariance -------

VARIANTS = {  # name: (old_logprobs in the batch, PolicyObjectiveConfig options)
    "on-policy": (False, {}),  # one update per batch: the detached current log-probs are pi_old
    "sync-tis": (False, {"is_cap": 1.5}),  # ... with TIS against the rollout engine's log-probs
    "decoupled-mask": (True, {"is_cap": 1.2, "is_cap_mode": "mask"}),
    "ppo": (True, {"clip_c": 3.0}),
}
MODES = ["token-mean", "seq-mean-token-sum", "seq-mean-token-mean", "seq-mean-token-sum-norm"]
WIDTH = 10


@pytest.fixture(scope="module")
def lm_batch(response_mask_factory):
    torch.manual_seed(0)
    model = TinyLM().to(F64)
    gen = torch.Generator().manual_seed(1)
    mask = response_mask_factory(gen, 8, WIDTH, empty_rows=1)
    ids = torch.randint(0, VOCAB, (8, WIDTH), generator=gen)
    with torch.no_grad():
        logp, _ = aligned_logprobs_and_entropy(model, ids)
    old = logp + 0.3 * torch.randn(8, WIDTH, generator=gen, dtype=F64)
    return model, {"ids": ids, "mask": mask, "old": old,
                   "rollout": logp + 0.4 * torch.randn(8, WIDTH, generator=gen, dtype=F64),
                   "ref": logp + 0.5 * torch.randn(8, WIDTH, generator=gen, dtype=F64),
                   "adv": torch.randn(8, WIDTH, generator=gen, dtype=F64)}


def objective_config(variant: str, mode: str) -> PolicyObjectiveConfig:
    return PolicyObjectiveConfig(clip_low=0.2, clip_high=0.28, aggregation=mode, kl_coef=0.1, kl_estimator="k3",
                                 entropy_coef=0.01, **VARIANTS[variant][1])


def normaliser_of(mask, mode):
    return aggregation_normaliser(mask, mode, **({"max_response_length": WIDTH} if mode.endswith("-norm") else {}))


def objective_loss(model, batch, rows, variant, mode, normaliser):
    logp, entropy = aligned_logprobs_and_entropy(model, batch["ids"][rows])
    micro = MicroBatch(response_mask=batch["mask"][rows], advantages=batch["adv"][rows],
                       rollout_logprobs=batch["rollout"][rows], ref_logprobs=batch["ref"][rows])
    if VARIANTS[variant][0]:
        micro["old_logprobs"] = batch["old"][rows]
    return policy_objective(micro, logp, entropy, objective_config(variant, mode), normaliser)[0]


def reference_objective(model, batch, variant, mode):
    """PPO clip (+ dual clip) x behaviour weight + kl_coef * k3 - entropy_coef * H per token, then
    the aggregation mode's textbook formula, in float64 loops of scalar ops (autograd gives the
    reference gradient). Without old log-probs pi_old is the detached current log-prob."""
    cfg = objective_config(variant, mode)
    logp, entropy = aligned_logprobs_and_entropy(model, batch["ids"])
    rows = []
    for i in range(logp.shape[0]):
        terms = []
        for t in range(logp.shape[1]):
            if not batch["mask"][i, t]:
                continue
            lp, a = logp[i, t], float(batch["adv"][i, t])
            old = float(batch["old"][i, t]) if VARIANTS[variant][0] else lp.item()
            ratio = torch.exp(lp - old)
            loss = torch.maximum(-a * ratio, -a * ratio.clamp(1 - cfg.clip_low, 1 + cfg.clip_high))
            if cfg.clip_c is not None and a < 0:
                loss = torch.minimum(loss, torch.tensor(-a * cfg.clip_c, dtype=F64))
            if cfg.is_cap is not None:
                w = math.exp(old - float(batch["rollout"][i, t]))
                loss = loss * (min(w, cfg.is_cap) if cfg.is_cap_mode == "truncate" else (0.0 if w > cfg.is_cap else w))
            log_r = float(batch["ref"][i, t]) - lp
            terms.append(loss + cfg.kl_coef * (torch.expm1(log_r) - log_r) - cfg.entropy_coef * entropy[i, t])
        if terms:
            rows.append(terms)
    tokens = sum(len(r) for r in rows)
    total = sum(sum(r) for r in rows)
    if mode == "token-mean":
        return total / tokens
    if mode == "seq-mean-token-sum":
        return total / len(rows)
    if mode == "seq-mean-token-mean":
        return sum(sum(r) / len(r) for r in rows) / len(rows)
    return total / (len(rows) * WIDTH)


def model_gradient(model, losses_of) -> list[torch.Tensor]:
    """The summed gradient of the losses ``losses_of(replica)`` yields, each rank on its own copy."""
    total = [torch.zeros_like(p) for p in model.parameters()]
    for losses in losses_of:
        replica = copy.deepcopy(model)
        for loss in losses(replica):
            loss.backward()
        for acc, p in zip(total, replica.parameters()):
            acc += p.grad
    return total


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_the_objective_matches_the_float64_reference_and_splits_invariantly(lm_batch, variant, mode):
    """Every aggregation mode with the KL and entropy terms on, with and without old log-probs
    (one on-policy update, with or without TIS), MIS: the whole mini-batch's gradient is the loop
    reference's, and two ranks with uneven micro-batches sum to it (the normaliser all-reduced)."""
    model, batch = lm_batch
    everything = list(range(8))
    normaliser = normaliser_of(batch["mask"], mode)
    whole = model_gradient(model, [lambda m: [objective_loss(m, batch, everything, variant, mode, normaliser)]])
    reference = model_gradient(model, [lambda m: [reference_objective(m, batch, variant, mode)]])
    assert max(float(g.abs().max()) for g in reference) > 1e-3  # a real gradient
    for got, expected in zip(whole, reference):
        torch.testing.assert_close(got, expected, atol=1e-10, rtol=1e-9)
    plan = [[[5], [0, 7]], [[1, 2, 3, 4, 6]]]  # rank 0: two micro-batches, rank 1: one
    shares = [sum(rank, []) for rank in plan]
    global_normaliser = sum(normaliser_of(batch["mask"][share], mode) for share in shares)
    assert global_normaliser == normaliser
    split = model_gradient(model, [lambda m, rank=rank: [objective_loss(m, batch, micro, variant, mode, normaliser)
                                                         for micro in rank] for rank in plan])
    for got, expected in zip(split, whole):
        torch.testing.assert_close(got, expected, atol=1e-10, rtol=0)
