"""Per-embodiment state normalisation: float64 references, split invariance, and the SAC agent's use of it."""

import copy

import numpy as np
import pytest
import torch

from infinirl.components.sac_learner import SACAgent, SACNetSpec, SACUpdateSpec
from infinirl.envs.base import ActionSpace
from infinirl.models.state_normalizer import EmbodimentStateNormalizer, NormalizedStateEncoder

OBS_DIM, KINDS = 7, 2  # 5 features (kind 0 uses all, kind 1 the first 3, zeros after) + a 2-kind one-hot
SPACE = ActionSpace.box([-1.0] * 3, [1.0] * 3)


def fleet_states(n=40, seed=0):
    """Rows of two robot kinds in very different units, padded and one-hot tagged as PolicyLayout does."""
    rng = np.random.default_rng(seed)
    kinds = rng.integers(0, KINDS, n)
    states = np.zeros((n, OBS_DIM), np.float32)
    for i, kind in enumerate(kinds):
        if kind == 0:
            states[i, :5] = rng.normal([0.1, -0.3, 0.2, 0.0, 0.5], 0.05)  # metres
        else:
            states[i, :3] = rng.normal([40.0, -90.0, 10.0], 25.0)  # degrees
        states[i, 5 + kind] = 1.0
    return states, kinds


def test_statistics_and_output_match_a_float64_reference_per_kind():
    states, kinds = fleet_states()
    norm = EmbodimentStateNormalizer(OBS_DIM, KINDS)
    norm.update(torch.from_numpy(states))
    out = norm(torch.from_numpy(states)).numpy()
    for kind in range(KINDS):
        rows = states[kinds == kind].astype(np.float64)[:, :5]
        n, eps = len(rows), 1e-4  # the statistics start as a pseudo-sample of weight 1e-4: mean 0, variance 1
        mean = rows.sum(0) / (n + eps)
        var = (eps * 1.0 + ((rows - mean) ** 2).sum(0) + eps * mean ** 2) / (n + eps)
        np.testing.assert_allclose(norm.stats[kind].mean.numpy(), mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(norm.stats[kind].var.numpy(), var, rtol=1e-9, atol=1e-12)
        expected = np.clip((rows - norm.stats[kind].mean.numpy()) / np.sqrt(norm.stats[kind].var.numpy() + 1e-8),
                           -10, 10)
        np.testing.assert_allclose(out[kinds == kind, :5], expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(out[:, 5:], states[:, 5:])  # the one-hot passes through
    assert np.all(out[kinds == 1, 3:5] == 0.0)  # kind 1's padding stays 0
    for kind in range(KINDS):  # each kind's features now have zero mean and unit variance where they vary
        rows = out[kinds == kind, :5 if kind == 0 else 3]
        np.testing.assert_allclose(rows.mean(0), 0.0, atol=1e-3)
        np.testing.assert_allclose(rows.std(0), 1.0, atol=5e-3)  # the prior pseudo-sample: within 0.3%


def test_statistics_do_not_depend_on_how_the_rows_are_split():
    states, _ = fleet_states(n=60, seed=1)
    whole, parts = EmbodimentStateNormalizer(OBS_DIM, KINDS), EmbodimentStateNormalizer(OBS_DIM, KINDS)
    whole.update(torch.from_numpy(states))
    for chunk in np.array_split(states, [7, 8, 30, 59]):
        parts.update(torch.from_numpy(chunk))
    for a, b in zip(whole.state_dict().values(), parts.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_one_embodiment_normalises_every_entry():
    norm = EmbodimentStateNormalizer(3)
    rows = torch.tensor([[1.0, 10.0, -5.0], [3.0, 30.0, -5.0]])
    norm.update(rows)
    out = norm(rows)
    torch.testing.assert_close(out[:, :2], torch.tensor([[-1.0, -1.0], [1.0, 1.0]]), rtol=1e-3, atol=1e-3)
    assert torch.all(out[:, 2].abs() < 0.05)  # a constant entry stays near 0 (the prior's pull only)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="embodiments"):
        EmbodimentStateNormalizer(4, 0)
    with pytest.raises(ValueError, match="no features"):
        EmbodimentStateNormalizer(2, 2)


def agent(seed=0):
    net = SACNetSpec(actor_hidden=(16,), critic_hidden=(16,), normalize_state=True)
    return SACAgent(net, SACUpdateSpec(seed=seed), OBS_DIM, SPACE, embodiments=KINDS)


def batch_of(states, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = len(states)
    obs = torch.from_numpy(states)
    return {"obs": obs, "next_obs": obs.roll(1, 0), "action": torch.rand(n, 3, generator=g) * 2 - 1,
            "reward": torch.randn(n, generator=g), "terminated": torch.zeros(n)}


def test_the_agent_folds_states_into_actor_critics_and_targets_and_a_robot_copy_acts_the_same():
    states, _ = fleet_states()
    a = agent()
    assert isinstance(a.actor.encoder, NormalizedStateEncoder) and a.critic.encoder is a.actor.encoder
    a.observe_states(states)
    for key, value in a.state_normalizer.state_dict().items():
        assert torch.equal(a.critic_target.encoder.normalizer.state_dict()[key], value), key
    a.update(batch_of(states))
    robot = SACNetSpec(actor_hidden=(16,), critic_hidden=(16,), normalize_state=True).build_actor(
        OBS_DIM, SPACE, embodiments=KINDS)
    robot.load_state_dict(a.actor.state_dict())  # what a weight sync hands a robot: statistics included
    obs = torch.from_numpy(states)
    torch.testing.assert_close(robot.sample(obs, deterministic=True)[0], a.actor.sample(obs, deterministic=True)[0])


def test_a_robot_kind_in_other_units_learns_the_same_as_in_its_own():
    """Normalised per kind, kind 1's states scaled by 100 and shifted (its readings in other units)
    give the networks the same inputs: the same updates, to float tolerance."""
    states, kinds = fleet_states(seed=2)
    other = states.copy()
    other[kinds == 1, :3] = other[kinds == 1, :3] * 100.0 + 7.0

    def run(rows, normalize=True):
        net = SACNetSpec(actor_hidden=(16,), critic_hidden=(16,), normalize_state=normalize)
        agent_ = SACAgent(net, SACUpdateSpec(seed=4), OBS_DIM, SPACE, embodiments=KINDS)
        agent_.observe_states(rows)
        for step in range(3):
            agent_.update(batch_of(rows, seed=step))
        return torch.cat([p.detach().reshape(-1) for p in [*agent_.critic.parameters(), *agent_.actor.parameters()]])

    torch.testing.assert_close(run(states), run(other), rtol=1e-4, atol=1e-4)
    assert (run(states, False) - run(other, False)).abs().max() > 1e-3  # raw: the units change what is learned


def test_statistics_resume_with_the_agent():
    states, _ = fleet_states()
    a = agent()
    a.observe_states(states[:20])
    b = agent(seed=9)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    a.observe_states(states[20:])
    b.observe_states(states[20:])
    for (name, x), (_, y) in zip(a.named_tensors(), b.named_tensors()):
        assert torch.equal(x, y), name


def test_without_the_option_the_networks_read_the_raw_state():
    a = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)), SACUpdateSpec(), OBS_DIM, SPACE,
                 embodiments=KINDS)
    assert a.state_normalizer is None and not hasattr(a.actor, "encoder")
    a.observe_states(fleet_states()[0])  # nothing to fold into
