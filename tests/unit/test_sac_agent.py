"""SAC's networks and one agent update, checked against straightforward references."""

import copy
import math

import numpy as np
import torch

from infinirl.components.sac_learner import SACAgent, SACNetSpec, SACUpdateSpec
from infinirl.envs.base import ActionSpace
from infinirl.models.sac_nets import EnsembleQ, SquashedGaussianActor

SPACE = ActionSpace.box([-3.0, -1.0], [3.0, 2.0])


def make_batch(n=16, obs_dim=5, action_dim=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"obs": torch.randn(n, obs_dim, generator=g), "action": torch.rand(n, action_dim, generator=g) * 2 - 1,
            "reward": torch.randn(n, generator=g), "next_obs": torch.randn(n, obs_dim, generator=g),
            "terminated": (torch.rand(n, generator=g) < 0.3).float()}


def test_squashed_gaussian_logprob_matches_change_of_variables():
    torch.manual_seed(0)
    actor = SquashedGaussianActor(5, 2, SPACE.low, SPACE.high, hidden=(16,))
    obs = torch.randn(64, 5)
    action, logprob, u = actor.sample(obs, torch.Generator().manual_seed(1))
    mean, log_std = actor.distribution(obs)
    reference = (torch.distributions.Normal(mean, log_std.exp()).log_prob(u)
                 - torch.log(1 - torch.tanh(u) ** 2)).sum(-1)
    torch.testing.assert_close(logprob, reference, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(actor.logprob_of(obs, u), logprob)
    assert action.abs().max() < 1 and torch.equal(action, torch.tanh(u))
    assert (log_std >= -5).all() and (log_std <= 2).all()
    env_action = actor.to_env(torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]]))
    torch.testing.assert_close(env_action, torch.tensor([[-3.0, -1.0], [3.0, 2.0], [0.0, 0.5]]))
    deterministic, _, u_det = actor.sample(obs, deterministic=True)
    torch.testing.assert_close(u_det, mean)
    # Far in the tails the stable form stays finite where the naive one is -inf.
    assert torch.isfinite(actor.logprob_of(obs[:1], torch.full((1, 2), 30.0))).all()


def test_ensemble_q_equals_independent_networks():
    torch.manual_seed(0)
    q = EnsembleQ(5, 2, hidden=(8, 8), num_critics=3)
    obs, action = torch.randn(10, 5), torch.rand(10, 2)
    out = q(obs, action)
    assert out.shape == (3, 10)
    for k in range(3):
        torch.testing.assert_close(out[k], member(q, k, torch.cat([obs, action], -1)))
    assert not torch.equal(q.layers[0].weight[0], q.layers[0].weight[1])  # independently initialised


def member(q, k, x, norm=lambda i, h: h):
    """Critic ``k`` of the ensemble as a plain MLP: linear, ``norm(layer index, h)``, relu."""
    for i, layer in enumerate(q.layers):
        x = x @ layer.weight[k] + layer.bias[k]
        if i < len(q.layers) - 1:
            x = torch.relu(norm(i, x))
    return x.squeeze(-1)


def test_ensemble_q_with_layer_norm_equals_independent_networks_with_torchs_layer_norm():
    """Each member: linear, ``torch.nn.LayerNorm`` with that member's own gain and bias, relu (float64)."""
    torch.manual_seed(0)
    q = EnsembleQ(5, 2, hidden=(8, 6), num_critics=2, layer_norm=True).double()
    for norm in q.norms:  # away from the ones/zeros they start at, different per member
        torch.nn.init.normal_(norm.weight)
        torch.nn.init.normal_(norm.bias)
    obs, action = torch.randn(10, 5, dtype=torch.float64), torch.rand(10, 2, dtype=torch.float64)
    out = q(obs, action)
    for k in range(2):
        def norm(i, h, k=k):
            reference = torch.nn.LayerNorm(h.shape[-1]).double()
            with torch.no_grad():
                reference.weight.copy_(q.norms[i].weight[k, 0])
                reference.bias.copy_(q.norms[i].bias[k, 0])
            return reference(h)

        torch.testing.assert_close(out[k], member(q, k, torch.cat([obs, action], -1), norm))
    actor = SquashedGaussianActor(5, 2, [-1, -1], [1, 1], hidden=(8,), layer_norm=True)
    assert any(isinstance(m, torch.nn.LayerNorm) for m in actor.trunk)
    plain = SquashedGaussianActor(5, 2, [-1, -1], [1, 1], hidden=(8,))
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in plain.trunk)


def test_update_matches_the_soft_bellman_reference_and_moves_targets_by_tau():
    spec = SACUpdateSpec(gamma=0.9, tau=0.1, init_alpha=0.5, seed=3)
    agent = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)), spec, 5, SPACE)
    batch = make_batch()
    critic_before, target_before = copy.deepcopy(agent.critic), copy.deepcopy(agent.critic_target)
    generator = torch.Generator()
    generator.set_state(agent.generator.get_state())
    with torch.no_grad():  # the reference target: y = r + gamma (1 - d) (min_k Q'_k(s', a') - alpha log pi(a'|s'))
        next_action, next_logprob, _ = copy.deepcopy(agent.actor).sample(batch["next_obs"], generator)
        next_q = target_before(batch["next_obs"], next_action).min(0).values
        y = batch["reward"] + 0.9 * (1 - batch["terminated"]) * (next_q - 0.5 * next_logprob)
        q = critic_before(batch["obs"], batch["action"])
        expected_loss = sum(0.5 * ((q[k] - y) ** 2).mean() for k in range(2))
    metrics = agent.update(batch)
    torch.testing.assert_close(metrics["train/critic_loss"], expected_loss)
    torch.testing.assert_close(metrics["train/q_target_mean"], y.mean())
    assert agent.updates == 1
    for old_target, new_critic, new_target in zip(target_before.parameters(), agent.critic.parameters(),
                                                  agent.critic_target.parameters()):
        torch.testing.assert_close(new_target, 0.9 * old_target + 0.1 * new_critic)
    assert all(p.requires_grad for p in agent.critic.parameters())  # unfrozen after the actor step
    assert not any(p.requires_grad for p in agent.critic_target.parameters())


def test_temperature_follows_the_entropy_target():
    for target, direction in ((-10.0, -1), (10.0, 1)):  # entropy above target: alpha falls; below: rises
        agent = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)),
                         SACUpdateSpec(init_alpha=0.2, target_entropy=target), 5, SPACE)
        for i in range(5):
            agent.update(make_batch(seed=i))
        assert direction * (float(agent.alpha) - 0.2) > 0
    fixed = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)),
                     SACUpdateSpec(init_alpha=0.2, autotune_alpha=False), 5, SPACE)
    fixed.update(make_batch())
    assert math.isclose(float(fixed.alpha), 0.2, rel_tol=1e-6)


def test_policy_delay_and_target_period():
    agent = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)),
                     SACUpdateSpec(policy_delay=2, target_update_every=3), 5, SPACE)
    actor_before = copy.deepcopy(agent.actor.state_dict())
    target_before = copy.deepcopy(agent.critic_target.state_dict())
    first = agent.update(make_batch(seed=1))
    assert "train/actor_loss" not in first
    assert all(torch.equal(actor_before[k], v) for k, v in agent.actor.state_dict().items())
    assert "train/actor_loss" in agent.update(make_batch(seed=2))
    assert all(torch.equal(target_before[k], v) for k, v in agent.critic_target.state_dict().items())
    agent.update(make_batch(seed=3))
    assert not all(torch.equal(target_before[k], v) for k, v in agent.critic_target.state_dict().items())


def test_state_dict_round_trip_continues_identically():
    spec = SACUpdateSpec(seed=5)
    a = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)), spec, 5, SPACE)
    for i in range(3):
        a.update(make_batch(seed=i))
    b = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)), SACUpdateSpec(seed=6), 5, SPACE)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    for i in range(3, 6):
        ma, mb = a.update(make_batch(seed=i)), b.update(make_batch(seed=i))
        assert {k: float(v) for k, v in ma.items()} == {k: float(v) for k, v in mb.items()}
    for (name, x), (_, y) in zip(a.named_tensors(), b.named_tensors()):
        assert torch.equal(x, y), name
    assert np.isfinite(float(a.alpha))


def test_sac_flow_actor_is_reparameterised_and_scores_its_own_path():
    from infinirl.models.sac_nets import FlowSACActor, squash_logprob_correction

    torch.manual_seed(0)
    actor = FlowSACActor(5, 2, SPACE.low, SPACE.high, num_steps=3, hidden=(16, 16))
    obs = torch.randn(8, 5)
    action, logprob, u = actor.sample(obs, torch.Generator().manual_seed(4))
    again, _, _ = actor.sample(obs, torch.Generator().manual_seed(4))
    assert torch.equal(action, again) and action.abs().max() < 1  # seeded by SAC's generator, squashed
    # The entropy term is the flow policy's own path log-density (+ the tanh change of variables):
    # re-scoring the same denoising path with FlowMatchingPolicy.evaluate gives the same number.
    generator = torch.Generator().manual_seed(4)
    seed = int(torch.randint(0, 2**62, (1,), generator=generator))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        step = actor.flow.act({"state": obs})
    scored = actor.flow.evaluate({"state": obs}, step.actions, step.extras).logprobs.sum(-1)
    torch.testing.assert_close(logprob, scored - squash_logprob_correction(u).sum(-1))
    # Reparameterised: the actor loss reaches the velocity network and the learned noise head.
    (logprob.mean() - actor.to_env(action).sum()).backward()
    grads = {name: p.grad for name, p in actor.named_parameters()}
    assert grads["flow.velocity_out.weight"].abs().sum() > 0 and grads["flow.noise_out.weight"].abs().sum() > 0

    agent = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,), actor="flow",
                                flow={"num_steps": 3, "hidden": (16, 16)}),
                     SACUpdateSpec(), 5, SPACE)
    before = copy.deepcopy(agent.actor.state_dict())
    metrics = agent.update(make_batch())
    assert np.isfinite(float(metrics["train/actor_loss"])) and np.isfinite(float(metrics["train/entropy"]))
    assert any(not torch.equal(before[k], v) for k, v in agent.actor.state_dict().items())


def test_masked_logprob_is_the_marginal_of_the_executed_entries():
    """A policy shared by robots of different action sizes: with a mask, the log-prob sums over the
    entries a sample's robot executes (float64 reference), and the unmasked path is unchanged."""
    torch.manual_seed(0)
    actor = SquashedGaussianActor(5, 3, [-1.0] * 3, [1.0] * 3, hidden=(16,)).double()
    obs = torch.randn(8, 5, dtype=torch.float64)
    mask = torch.tensor([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]] * 4, dtype=torch.float64)
    _, full, u = actor.sample(obs, torch.Generator().manual_seed(1))
    _, masked, u_masked = actor.sample(obs, torch.Generator().manual_seed(1), mask=mask)
    assert torch.equal(u, u_masked)
    mean, log_std = actor.distribution(obs)
    per_entry = torch.distributions.Normal(mean, log_std.exp()).log_prob(u) - torch.log(1 - torch.tanh(u) ** 2)
    torch.testing.assert_close(masked, (per_entry * mask).sum(-1), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(full, per_entry.sum(-1), rtol=1e-10, atol=1e-10)


def test_with_an_action_mask_the_padding_entries_change_nothing_the_agent_learns():
    """The critics see the executed entries only (padding zeroed), the temperature's target counts
    them: two batches that differ only in padding entries give the same update."""
    from infinirl.realworld.control_loop import EmbodimentActionMask

    obs_dim, action_dim = 6, 3  # the state's last two entries: a one-hot of two kinds
    mask_of = EmbodimentActionMask(obs_dim, action_dim, (3, 2))
    batch = make_batch(n=16, obs_dim=obs_dim, action_dim=action_dim)
    kinds = torch.arange(16) % 2
    for key in ("obs", "next_obs"):
        batch[key][:, -2:] = torch.nn.functional.one_hot(kinds, 2).float()
    mask = mask_of(batch["obs"])
    assert torch.equal(mask, torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 0.0]] * 8))
    other = {**batch, "action": batch["action"].clone()}
    other["action"][kinds == 1, 2] = 0.77  # kind 1 does not execute entry 2

    def run(b, mask=mask_of):
        agent = SACAgent(SACNetSpec(actor_hidden=(16,), critic_hidden=(16,)), SACUpdateSpec(seed=3), obs_dim,
                         ActionSpace.box([-1.0] * action_dim, [1.0] * action_dim), action_mask=mask)
        for _ in range(3):
            agent.update(b)
        return torch.cat([p.detach().reshape(-1) for p in [*agent.critic.parameters(), *agent.actor.parameters(),
                                                          agent.log_alpha]])

    torch.testing.assert_close(run(batch), run(other), rtol=0, atol=0)
    assert not torch.equal(run(batch, None), run(other, None))  # without the mask the padding is data
