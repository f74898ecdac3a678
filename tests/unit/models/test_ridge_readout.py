"""RidgeReadout against a float64 reference of standardised ridge regression, split-invariance of its
running sums, and its edge cases (unfitted, constant columns, bad arguments)."""

import numpy as np
import pytest
import torch

from infinirl.models.ridge_readout import RidgeReadout


def _data(n=300, f=12, t=3, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, f)) * rng.uniform(0.01, 50.0, size=f) + rng.normal(size=f) * 10
    y = x @ rng.normal(size=(f, t)) + 0.1 * rng.normal(size=(n, t)) + 3.0
    return x, y


def _reference(x, y, penalty, query):
    """Standardised ridge written out directly: coefficients on z-scored inputs, prediction
    z-scored by the targets' (population) mean and std."""
    mx, sx = x.mean(0), x.std(0)
    my, sy = y.mean(0), y.std(0)
    z = (x - mx) / sx
    coef = np.linalg.solve(z.T @ z / len(x) + penalty * np.eye(x.shape[1]), z.T @ (y - my) / len(x))
    return ((query - mx) / sx) @ coef / sy


@pytest.mark.parametrize("penalty", [1e-4, 1e-2, 1.0])
def test_matches_float64_reference(penalty):
    x, y = _data()
    readout = RidgeReadout(x.shape[1], y.shape[1], penalty=penalty, clip=1e9)
    readout.accumulate(torch.tensor(x), torch.tensor(y))
    readout.refit()
    query, _ = _data(n=50, seed=1)
    got = readout(torch.tensor(query, dtype=torch.float64)).double().numpy()
    np.testing.assert_allclose(got, _reference(x, y, penalty, query), rtol=1e-5, atol=1e-5)


def test_sums_are_split_invariant():
    x, y = _data()
    whole = RidgeReadout(x.shape[1], y.shape[1])
    whole.accumulate(torch.tensor(x), torch.tensor(y))
    parts = RidgeReadout(x.shape[1], y.shape[1])
    for rows in (slice(0, 7), slice(7, 160), slice(160, 300)):
        parts.accumulate(torch.tensor(x[rows]), torch.tensor(y[rows]))
    whole.refit()
    parts.refit()
    torch.testing.assert_close(parts.weight, whole.weight, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(parts.bias, whole.bias, rtol=1e-9, atol=1e-12)


def test_recovers_a_linear_map_and_scores_it_held_out():
    x, y = _data(n=2000)
    readout = RidgeReadout(x.shape[1], y.shape[1], penalty=1e-6)
    assert np.isnan(readout.score(torch.tensor(x), torch.tensor(y)))  # unfitted
    readout.accumulate(torch.tensor(x[:1500]), torch.tensor(y[:1500]))
    readout.refit()
    assert readout.score(torch.tensor(x[1500:]), torch.tensor(y[1500:])) > 0.999
    shuffled = np.random.default_rng(3).permutation(y[1500:])
    assert readout.score(torch.tensor(x[1500:]), torch.tensor(shuffled)) < 0.0


def test_unfitted_reads_zeros_and_refit_waits_for_rows():
    readout = RidgeReadout(4, 2)
    assert not readout.fitted
    torch.testing.assert_close(readout(torch.ones(3, 4)), torch.zeros(3, 2))
    readout.refit()  # nothing accumulated: still unfitted
    assert not readout.fitted


def test_constant_columns_read_zero_and_do_not_break_the_solve():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(size=(100, 3)), np.full((100, 1), 7.0)], axis=1)
    y = np.stack([x[:, 0] * 2, np.zeros(100)], axis=1)
    readout = RidgeReadout(4, 2, penalty=1e-6)
    readout.accumulate(torch.tensor(x), torch.tensor(y))
    readout.refit()
    out = readout(torch.tensor(x))
    assert torch.isfinite(out).all()
    assert torch.all(out[:, 1] == 0)
    assert torch.all(readout.weight[0, 3] == 0)  # the constant input carries no weight
    np.testing.assert_allclose(out[:, 0].numpy(), (x[:, 0] - x[:, 0].mean()) / x[:, 0].std(), atol=1e-4)


def test_output_is_clipped_and_float32():
    x, y = _data()
    readout = RidgeReadout(x.shape[1], y.shape[1], clip=0.5)
    readout.accumulate(torch.tensor(x), torch.tensor(y))
    readout.refit()
    out = readout(torch.tensor(x, dtype=torch.float32))
    assert out.dtype == torch.float32 and out.abs().max() <= 0.5


def test_its_sums_stay_float64_when_the_module_is_cast():
    x, y = _data()
    readout = RidgeReadout(x.shape[1], y.shape[1])
    readout.accumulate(torch.tensor(x), torch.tensor(y))
    readout.refit()
    before = readout(torch.tensor(x[:4], dtype=torch.float32))
    wrapper = torch.nn.Sequential(readout).to(torch.bfloat16).float()
    assert all(buffer.dtype == torch.float64 for name, buffer in wrapper[0].named_buffers() if name != "keys")
    torch.testing.assert_close(wrapper[0](torch.tensor(x[:4], dtype=torch.float32)), before)


def test_state_dict_round_trip_keeps_the_fit():
    x, y = _data()
    readout = RidgeReadout(x.shape[1], y.shape[1])
    readout.accumulate(torch.tensor(x), torch.tensor(y))
    readout.refit()
    copy = RidgeReadout(x.shape[1], y.shape[1])
    copy.load_state_dict(readout.state_dict())
    query = torch.tensor(x[:5], dtype=torch.float32)
    torch.testing.assert_close(copy(query), readout(query))


@pytest.mark.parametrize("kwargs, match", [
    ({"in_dim": 0, "out_dim": 2}, "in_dim, out_dim and groups >= 1"),
    ({"in_dim": 3, "out_dim": 2, "penalty": 0.0}, "penalty must be > 0"),
])
def test_bad_arguments_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RidgeReadout(**kwargs)


def test_rows_must_pair_up():
    with pytest.raises(ValueError, match="3 input rows against 2 target rows"):
        RidgeReadout(4, 2).accumulate(torch.zeros(3, 4), torch.zeros(2, 2))


def test_groups_fit_one_readout_per_key_as_separate_readouts_would():
    """Rows keyed by group: each group's fit is the one a readout of its rows alone gives, keys
    take groups in order of first appearance, an unknown key reads 0 and is left out of the score,
    and more keys than groups are refused."""
    (xa, ya), (xb, yb) = _data(seed=0), _data(seed=5)
    grouped = RidgeReadout(xa.shape[1], ya.shape[1], groups=3)
    x, y = torch.tensor(np.concatenate([xa, xb])), torch.tensor(np.concatenate([ya, yb]))
    keys = torch.tensor([7] * len(xa) + [3] * len(xb))
    order = torch.randperm(len(x), generator=torch.Generator().manual_seed(0))
    grouped.accumulate(x[order[:250]], y[order[:250]], keys[order[:250]])
    grouped.accumulate(x[order[250:]], y[order[250:]], keys[order[250:]])
    grouped.refit()
    assert grouped.keys.tolist() == [3, 7, 0]  # sorted within the first batch
    for key, (xs, ys) in ((7, (xa, ya)), (3, (xb, yb))):
        alone = RidgeReadout(xs.shape[1], ys.shape[1])
        alone.accumulate(torch.tensor(xs), torch.tensor(ys))
        alone.refit()
        query = torch.tensor(xs[:20])
        torch.testing.assert_close(grouped(query, torch.full((20,), key)), alone(query), rtol=1e-6, atol=1e-6)
    assert torch.all(grouped(torch.tensor(xa[:4]), torch.full((4,), 99)) == 0)
    mixed_keys = torch.tensor([7] * 300 + [99] * 300)
    noisy_y = np.concatenate([ya, np.random.default_rng(1).normal(size=ya.shape) * 1e3])
    assert grouped.score(torch.tensor(np.concatenate([xa, xa])), torch.tensor(noisy_y), mixed_keys) > 0.99
    grouped.accumulate(torch.tensor(xa[:2]), torch.tensor(ya[:2]), torch.tensor([11, 11]))  # the third group
    with pytest.raises(ValueError, match="holds 3 groups and a batch brings 4 keys: raise its groups"):
        grouped.accumulate(torch.tensor(xa[:2]), torch.tensor(ya[:2]), torch.tensor([12, 12]))
    with pytest.raises(ValueError, match="groups=3 needs a key per row"):
        grouped(torch.tensor(xa[:2]))
