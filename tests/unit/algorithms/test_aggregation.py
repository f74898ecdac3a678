"""Loss aggregation: loop references per mode, and the micro-batch / data-parallel invariance of the
gradient of a real (tiny) model's PPO + KL + entropy objective under every mode (and with the plain
policy gradient, the k1 / k2 estimators and MIS's masked weights)."""

import copy

import pytest
import torch

from infinirl.algorithms import (
    AGGREGATIONS,
    POLICY_LOSSES,
    aggregate,
    aggregate_locally,
    aggregation_normaliser,
    entropy_from_logits,
    entropy_loss,
    kl_loss,
    ppo_clip_loss,
)

F64 = torch.float64
MODES = ["token-mean", "seq-mean-token-sum", "seq-mean-token-mean", "seq-mean-token-sum-norm"]
MAX_LEN = 10


def mode_kwargs(mode):
    return {"max_response_length": MAX_LEN} if mode == "seq-mean-token-sum-norm" else {}


def ref_aggregate(loss, mask, mode):
    """The textbook definition of each mode over one whole batch, with loops."""
    rows = []
    for i in range(loss.shape[0]):
        values = [float(loss[i, t]) for t in range(loss.shape[1]) if mask[i, t]]
        if values:
            rows.append(values)
    if mode == "token-mean":
        return sum(sum(r) for r in rows) / sum(len(r) for r in rows)
    if mode == "seq-mean-token-sum":
        return sum(sum(r) for r in rows) / len(rows)
    if mode == "seq-mean-token-mean":
        return sum(sum(r) / len(r) for r in rows) / len(rows)
    if mode == "seq-mean-token-sum-norm":
        return sum(sum(r) / MAX_LEN for r in rows) / len(rows)
    raise AssertionError(mode)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_aggregate_matches_reference(response_mask_factory, mode, seed):
    gen = torch.Generator().manual_seed(seed)
    mask = response_mask_factory(gen, 7, MAX_LEN, empty_rows=2)
    loss = torch.randn(7, MAX_LEN, generator=gen, dtype=F64)
    loss[mask == 0] = float("inf")  # masked entries must not leak, even when not finite
    value = aggregate_locally(loss, mask, mode, **mode_kwargs(mode))
    assert float(value) == pytest.approx(ref_aggregate(loss, mask, mode), rel=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_normaliser_is_additive_over_shards(response_mask_factory, mode):
    gen = torch.Generator().manual_seed(5)
    mask = response_mask_factory(gen, 9, MAX_LEN, empty_rows=2)
    whole = aggregation_normaliser(mask, mode, **mode_kwargs(mode))
    shards = sum(aggregation_normaliser(part, mode, **mode_kwargs(mode))
                 for part in (mask[:2], mask[2:7], mask[7:]))
    assert whole == shards > 0


def test_normaliser_values_by_hand():
    mask = torch.tensor([[0, 1, 1, 0], [0, 0, 0, 0], [1, 1, 1, 1]])
    assert aggregation_normaliser(mask, "token-mean") == 6
    assert aggregation_normaliser(mask, "seq-mean-token-sum") == 2  # the empty row does not count
    assert aggregation_normaliser(mask, "seq-mean-token-mean") == 2
    assert aggregation_normaliser(mask, "seq-mean-token-sum-norm", max_response_length=16) == 32


def test_zero_normaliser_gives_zero_loss_still_in_graph():
    loss = torch.ones(2, 3, dtype=F64, requires_grad=True)
    out = aggregate(loss, torch.zeros(2, 3), "token-mean", 0.0)
    out.backward()
    assert out.item() == 0.0 and torch.equal(loss.grad, torch.zeros(2, 3, dtype=F64))


@pytest.mark.parametrize("normaliser", [0.0, 5.0])
def test_a_tensor_normaliser_gives_what_the_float_gives(normaliser):
    """A 0-dim tensor normaliser (an all-reduced count, or one computed inside a compiled loss)
    takes a branch-free path; it must agree with the float one, 0 included (loss 0, no NaN grad)."""
    mask = torch.tensor([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]]) if normaliser else torch.zeros(2, 3)
    results = []
    for n in (normaliser, torch.tensor(normaliser, dtype=F64)):
        loss = torch.arange(6, dtype=F64).reshape(2, 3).requires_grad_()
        out = aggregate(loss, mask, "token-mean", n)
        out.backward()
        results.append((out.detach(), loss.grad))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
    assert torch.isfinite(results[1][1]).all()
    assert float(results[1][0]) == (0.0 if not normaliser else (0 + 1 + 3 + 4 + 5) / 5.0)


def test_aggregation_errors():
    with pytest.raises(KeyError, match="unknown loss aggregation mode 'token_mean'; registered: "
                                       "seq-mean-token-mean, seq-mean-token-sum, "
                                       "seq-mean-token-sum-norm, token-mean"):
        aggregation_normaliser(torch.ones(1, 1), "token_mean")
    with pytest.raises(TypeError, match="seq-mean-token-sum-norm.*max_response_length"):
        aggregation_normaliser(torch.ones(1, 1), "seq-mean-token-sum-norm")
    with pytest.raises(ValueError, match="same shape"):
        aggregate(torch.ones(2, 3), torch.ones(2, 4), "token-mean", 1.0)
    assert sorted(AGGREGATIONS.names()) == sorted(MODES)


def test_one_dimensional_per_sample_losses_are_supported():
    loss = torch.tensor([1.0, 2.0, 4.0], dtype=F64)
    mask = torch.tensor([1.0, 0.0, 1.0], dtype=F64)
    assert float(aggregate_locally(loss, mask, "token-mean")) == 2.5


# --- invariance with a real model --------------------------------------------------------------

VOCAB, DIM, BATCH = 11, 6, 8


class TinyLM(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.embed = torch.nn.Embedding(VOCAB, DIM)
        self.head = torch.nn.Linear(DIM, VOCAB)

    def forward(self, ids):
        return self.head(torch.tanh(self.embed(ids)))


def aligned_logprobs_and_entropy(model, ids):
    """Shift logits once so entry t scores token t (the batch.py alignment); position 0 is 0."""
    logits = model(ids)[:, :-1]
    logp = torch.log_softmax(logits, dim=-1).gather(-1, ids[:, 1:, None]).squeeze(-1)
    pad = logp.new_zeros(ids.shape[0], 1)
    return torch.cat([pad, logp], dim=1), torch.cat([pad, entropy_from_logits(logits)], dim=1)


@pytest.fixture(scope="module")
def rl_batch(response_mask_factory):
    torch.manual_seed(0)
    model = TinyLM().to(F64)
    gen = torch.Generator().manual_seed(1)
    mask = response_mask_factory(gen, BATCH, MAX_LEN, empty_rows=1)
    ids = torch.randint(0, VOCAB, (BATCH, MAX_LEN), generator=gen)
    with torch.no_grad():
        logp, _ = aligned_logprobs_and_entropy(model, ids)
    # old log-probs off the model's so that some ratios leave the clip range
    old = logp + 0.3 * torch.randn(BATCH, MAX_LEN, generator=gen, dtype=F64)
    batch = {
        "ids": ids, "mask": mask, "old": old,
        "behaviour": old + 0.2 * torch.randn(BATCH, MAX_LEN, generator=gen, dtype=F64),
        "ref": logp + 0.2 * torch.randn(BATCH, MAX_LEN, generator=gen, dtype=F64),
        "adv": torch.randn(BATCH, MAX_LEN, generator=gen, dtype=F64),
    }
    return model, batch


def micro_batch_loss(model, batch, rows, mode, normaliser):
    pick = {key: value[rows] for key, value in batch.items()}
    logp, entropy = aligned_logprobs_and_entropy(model, pick["ids"])
    policy = ppo_clip_loss(
        logprobs=logp, old_logprobs=pick["old"], advantages=pick["adv"], response_mask=pick["mask"],
        clip_low=0.2, clip_high=0.28, clip_c=3.0, behaviour_logprobs=pick["behaviour"], is_cap=2.0,
    )
    total = (policy.loss_mat + 0.1 * kl_loss(logp, pick["ref"], pick["mask"])
             + 0.01 * entropy_loss(pick["mask"], entropy=entropy).loss_mat)
    return aggregate(total, pick["mask"], mode, normaliser)


def gradient(model, batch, plan, mode, loss_of=micro_batch_loss):
    """``plan``: one list per DP rank, each a list of micro-batches (row lists). Each rank works on
    its own model copy and computes the normaliser over its share; normalisers are all-reduced with
    SUM, and so are the gradients, as the aggregation contract says."""
    shares = [[row for micro in rank for row in micro] for rank in plan]
    normaliser = sum(aggregation_normaliser(batch["mask"][share], mode, **mode_kwargs(mode))
                     for share in shares)
    total = [torch.zeros_like(p) for p in model.parameters()]
    for rank in plan:
        replica = copy.deepcopy(model)
        for micro in rank:
            loss_of(replica, batch, micro, mode, normaliser).backward()
        for acc, param in zip(total, replica.parameters()):
            acc += param.grad
    return total


PLANS = {
    "1x8": [[list(range(8))]],
    "8x1": [[[i] for i in range(8)]],
    "2x4": [[[0, 1, 2, 3], [4, 5, 6, 7]]],
    "dp2": [[[0, 1, 2, 3]], [[4, 5, 6, 7]]],
    "dp2x2": [[[0, 1], [2, 3]], [[4, 5], [6, 7]]],
    "dp2-uneven": [[[5], [0, 7]], [[1, 2, 3, 4, 6]]],
}


@pytest.fixture(scope="module")
def full_batch_gradient(rl_batch):
    """The 1 rank x 1 micro-batch gradient per mode, computed once for all plans."""
    model, batch = rl_batch
    return {mode: gradient(model, batch, PLANS["1x8"], mode) for mode in MODES}


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("plan", [p for p in PLANS if p != "1x8"])
def test_gradient_is_invariant_to_micro_batching_and_data_parallel(
    rl_batch, full_batch_gradient, mode, plan
):
    model, batch = rl_batch
    reference = full_batch_gradient[mode]
    split = gradient(model, batch, PLANS[plan], mode)
    assert any(float(g.abs().max()) > 1e-3 for g in reference)  # a real, non-trivial gradient
    for ref_grad, split_grad in zip(reference, split):
        torch.testing.assert_close(split_grad, ref_grad, atol=1e-9, rtol=0)


def other_loss(policy: str, estimator: str, cap_mode: str):
    """A micro-batch loss like :func:`micro_batch_loss` with another policy loss, KL estimator and
    behaviour-weight cap mode."""

    def loss_of(model, batch, rows, mode, normaliser):
        pick = {key: value[rows] for key, value in batch.items()}
        logp, _ = aligned_logprobs_and_entropy(model, pick["ids"])
        policy_loss = POLICY_LOSSES.get(policy)(
            logprobs=logp, old_logprobs=pick["old"], advantages=pick["adv"], response_mask=pick["mask"],
            behaviour_logprobs=pick["behaviour"], is_cap=1.2, is_cap_mode=cap_mode,
        )
        total = policy_loss.loss_mat + 0.1 * kl_loss(logp, pick["ref"], pick["mask"], estimator=estimator)
        return aggregate(total, pick["mask"], mode, normaliser)

    return loss_of


@pytest.mark.parametrize("mode", ["token-mean", "seq-mean-token-mean"])
@pytest.mark.parametrize("policy, estimator, cap_mode", [
    ("policy_gradient", "k1", "truncate"), ("policy_gradient", "k2", "mask"), ("ppo_clip", "k1", "mask"),
])
def test_other_losses_estimators_and_cap_modes_are_invariant_too(rl_batch, mode, policy, estimator, cap_mode):
    model, batch = rl_batch
    loss_of = other_loss(policy, estimator, cap_mode)
    reference = gradient(model, batch, PLANS["1x8"], mode, loss_of)
    assert any(float(g.abs().max()) > 1e-3 for g in reference)
    for plan in ("8x1", "dp2-uneven"):
        for ref_grad, split_grad in zip(reference, gradient(model, batch, PLANS[plan], mode, loss_of)):
            torch.testing.assert_close(split_grad, ref_grad, atol=1e-9, rtol=0)


@pytest.mark.parametrize("mode", MODES)
def test_full_batch_loss_is_the_textbook_aggregate(rl_batch, mode):
    model, batch = rl_batch
    rows = list(range(BATCH))
    normaliser = aggregation_normaliser(batch["mask"], mode, **mode_kwargs(mode))
    value = micro_batch_loss(model, batch, rows, mode, normaliser)
    per_micro = sum(micro_batch_loss(model, batch, [i], mode, normaliser).item() for i in rows)
    assert value.item() == pytest.approx(per_micro, rel=1e-12)


def test_naive_per_micro_batch_mean_is_not_invariant(rl_batch, full_batch_gradient):
    """The control: local normalisers (what the global one exists to avoid) change the gradient,
    so the invariance test above can fail."""
    model, batch = rl_batch
    reference = full_batch_gradient["token-mean"]
    replica = copy.deepcopy(model)
    micro_batches = PLANS["8x1"][0]
    for micro in micro_batches:
        local = aggregation_normaliser(batch["mask"][micro], "token-mean")
        loss = micro_batch_loss(replica, batch, micro, "token-mean", local)
        (loss / len(micro_batches)).backward()
    naive = [p.grad for p in replica.parameters()]
    assert max(float((a - b).abs().max()) for a, b in zip(naive, reference)) > 1e-4
