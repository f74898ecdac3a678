"""Flow-matching policy: the log-prob of a sampled chunk is the sum of its Gaussian denoising
transitions, checked against a float64 loop that writes each step in Flow-GRPO's own convention
(noise level ``s = 1 - tau``, velocity pointing to noise), so the convention change is tested too."""

import math

import pytest
import torch

from infinirl.models.policies.base import build_policy
from infinirl.models.policies.flow import flow_sde_sigmas, flow_sde_transition, flow_timesteps

SMALL = dict(hidden=(32, 32), value_hidden=(32,), time_dim=16)


def state_obs(batch=4, dim=3, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return {"state": torch.randn(batch, dim, generator=generator)}


def flow_policy(**kwargs):
    options = dict(action_dim=2, chunk=3, obs_dim=3, num_steps=4, **SMALL)
    options.update(kwargs)
    return build_policy("flow_matching", **options)


def reference_logprob(policy, obs, chain, mask):
    """Loop over samples and steps; each transition in Flow-GRPO's form (their eq. 9 code)."""
    features = policy.encoder(obs).double()
    batch, _, chunk, dims = chain.shape
    steps, a = policy.num_steps, policy.noise_level
    total = torch.zeros(batch, chunk, dtype=torch.float64)
    for b in range(batch):
        for k in range(steps):
            if not mask[b, k]:
                continue
            x = chain[b : b + 1, k].double()
            tau = k / steps
            v, learned_std = policy.velocity(x, torch.tensor([tau], dtype=torch.float64), features[b : b + 1])
            if policy.noise_method == "flow_sde":
                sigma, sigma_prev, sigma_max = 1 - tau, 1 - (k + 1) / steps, 1 - 1 / steps
                dt = sigma_prev - sigma  # negative: noise level goes down
                std_dev = math.sqrt(sigma / (1 - (sigma_max if sigma == 1 else sigma))) * a
                model_output = -v  # Flow-GRPO's velocity points from data to noise
                mean = x * (1 + std_dev**2 / (2 * sigma) * dt) + model_output * (
                    1 + std_dev**2 * (1 - sigma) / (2 * sigma)) * dt
                std = torch.full_like(mean, std_dev * math.sqrt(-dt))
            else:
                mean, std = x + v / steps, learned_std
            for c in range(chunk):
                for d in range(dims):
                    value = chain[b, k + 1, c, d].double()
                    total[b, c] += (-(value - mean[0, c, d]) ** 2 / (2 * std[0, c, d] ** 2)
                                    - torch.log(std[0, c, d]) - 0.5 * math.log(2 * math.pi))
    return total


@pytest.mark.parametrize("noise_method", ["flow_sde", "flow_noise"])
@pytest.mark.parametrize("sde_steps", ["all", "one"])
def test_act_logprob_is_sum_of_transitions_and_evaluate_recomputes_it(noise_method, sde_steps):
    torch.manual_seed(0)
    policy = flow_policy(noise_method=noise_method, sde_steps=sde_steps, noise_level=0.7).double()
    obs = state_obs()
    step = policy.act(obs)
    chain, mask = step.extras["chain"], step.extras["sde_mask"]
    assert step.actions.shape == (4, 3, 2) and step.logprobs.shape == (4, 3) and step.values.shape == (4,)
    assert chain.shape == (4, 5, 3, 2) and mask.shape == (4, 4)
    assert torch.equal(chain[:, -1], step.actions)
    assert mask.sum(1).tolist() == ([4] * 4 if sde_steps == "all" else [1] * 4)
    reference = reference_logprob(policy, obs, chain, mask)
    torch.testing.assert_close(step.logprobs, reference, rtol=1e-10, atol=1e-10)
    evaluation = policy.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluation.logprobs, reference, rtol=1e-10, atol=1e-10)
    assert evaluation.entropy.shape == (4, 3)


def test_float32_act_and_evaluate_agree():
    torch.manual_seed(1)
    policy = flow_policy(num_steps=10, chunk=4)
    obs = state_obs(batch=16)
    with torch.no_grad():
        step = policy.act(obs)
    evaluation = policy.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluation.logprobs, step.logprobs, rtol=1e-5, atol=1e-4)


def test_ode_steps_between_stochastic_ones_follow_the_velocity():
    torch.manual_seed(0)
    policy = flow_policy(sde_steps="one")
    obs = state_obs()
    step = policy.act(obs)
    chain, mask = step.extras["chain"], step.extras["sde_mask"]
    features = policy.encoder(obs)
    for k in range(policy.num_steps):
        v, _ = policy.velocity(chain[:, k], torch.full((4,), k / 4), features)
        ode = chain[:, k] + v / 4
        deterministic_rows = ~mask[:, k]
        torch.testing.assert_close(chain[deterministic_rows, k + 1], ode[deterministic_rows])


def test_deterministic_act_is_the_euler_ode_and_repeatable():
    torch.manual_seed(0)
    policy = flow_policy()
    obs = state_obs()
    torch.manual_seed(5)
    first = policy.act(obs, deterministic=True)
    torch.manual_seed(5)
    second = policy.act(obs, deterministic=True)
    torch.testing.assert_close(first.actions, second.actions, rtol=0, atol=0)
    chain = first.extras["chain"]
    features = policy.encoder(obs)
    x = chain[:, 0]
    for k in range(4):
        x = x + policy.velocity(x, torch.full((4,), k / 4), features)[0] / 4
    torch.testing.assert_close(first.actions, x)
    torch.testing.assert_close(policy.evaluate(obs, first.actions, first.extras).logprobs, first.logprobs,
                               rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("noise_method", ["flow_sde", "flow_noise"])
def test_evaluate_gradient_reaches_every_parameter(noise_method):
    torch.manual_seed(0)
    policy = flow_policy(noise_method=noise_method)
    obs = state_obs()
    with torch.no_grad():
        step = policy.act(obs)
    evaluation = policy.evaluate(obs, step.actions, step.extras)
    loss = evaluation.logprobs.sum() + evaluation.values.sum() + evaluation.entropy.sum()
    loss.backward()
    missing = [name for name, p in policy.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing, f"no gradient reached {missing}"
    assert (policy.noise_out is not None) == (noise_method == "flow_noise")


def test_image_encoder_with_separate_critic():
    torch.manual_seed(0)
    policy = flow_policy(obs_dim=3, obs_key="proprio", image_shape=(64, 64, 3), channels=(8, 16, 16),
                         features=32, separate_critic=True)
    obs = {"rgb": torch.randint(0, 256, (2, 64, 64, 3), dtype=torch.uint8), "proprio": torch.randn(2, 3)}
    step = policy.act(obs)
    assert step.actions.shape == (2, 3, 2) and step.values.shape == (2,)
    torch.testing.assert_close(policy.value(obs), step.values)
    evaluation = policy.evaluate(obs, step.actions, step.extras)
    (evaluation.logprobs.sum() + evaluation.values.sum()).backward()
    assert all(p.grad is not None for p in policy.critic_encoder.parameters())


def test_evaluate_scores_the_given_actions_and_checks_the_chain():
    torch.manual_seed(0)
    policy = flow_policy()
    obs = state_obs()
    step = policy.act(obs)
    moved = policy.evaluate(obs, step.actions + 0.5, step.extras).logprobs
    assert (moved < step.logprobs - 1e-3).all()  # the last transition is now less likely
    with pytest.raises(ValueError, match="extras"):
        policy.evaluate(obs, step.actions)
    with pytest.raises(ValueError, match="denoising steps"):
        policy.evaluate(obs, step.actions, {"chain": step.extras["chain"][:, 1:]})


def test_constructor_rejects_bad_options():
    with pytest.raises(ValueError, match="noise_method"):
        flow_policy(noise_method="ddim")
    with pytest.raises(ValueError, match="sde_steps"):
        flow_policy(sde_steps="two")
    with pytest.raises(ValueError, match="noise_level"):
        flow_policy(noise_level=0.0)
    with pytest.raises(ValueError, match="image"):
        flow_policy(obs_dim=0)


def test_flow_sde_preserves_the_ode_marginals():
    """With the exact velocity of a Gaussian data distribution, the SDE sampler ends at that
    distribution; dropping the score correction (plain noise injection) inflates its spread."""
    torch.manual_seed(0)
    mu, s = 1.5, 0.3

    def velocity(x, tau):  # E[a - eps | x_tau] for a ~ N(mu, s^2), x_tau = tau a + (1 - tau) eps
        variance = tau**2 * s**2 + (1 - tau) ** 2
        centred = x - tau * mu
        return mu + tau * s**2 * centred / variance - (1 - tau) * centred / variance

    steps = 100
    timesteps = flow_timesteps(steps, torch.float64)
    sigmas = flow_sde_sigmas(timesteps, 0.7)
    assert math.isclose(sigmas[0].item() * math.sqrt(1 / steps), 0.7)  # first std = noise_level
    x = torch.randn(20000, dtype=torch.float64)
    naive = x.clone()
    for k in range(steps):
        tau, dtau = timesteps[k], timesteps[k + 1] - timesteps[k]
        mean, std = flow_sde_transition(x, velocity(x, tau), tau, dtau, sigmas[k])
        x = mean + std * torch.randn_like(x)
        naive = naive + velocity(naive, tau) * dtau + std * torch.randn_like(x)
    assert abs(x.mean().item() - mu) < 0.01 and abs(x.std().item() - s) < 0.01
    assert naive.std().item() > 2 * s


def test_bc_loss_pretrains_towards_demonstrations():
    torch.manual_seed(0)
    policy = flow_policy(action_dim=2, chunk=2, obs_dim=3, num_steps=8, hidden=(64, 64))
    obs = {"state": torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])}
    demos = torch.tensor([[[0.5, -0.5], [0.3, 0.1]], [[-0.4, 0.6], [0.0, -0.7]]])
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-2)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda i: 1 - i / 300)  # settles the noisy loss
    batch = {"state": obs["state"].repeat(32, 1)}
    targets = demos.repeat(32, 1, 1)
    for _ in range(300):
        loss = policy.bc_loss(batch, targets)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
    torch.manual_seed(1)  # the ODE starts from noise; every start should land near the demo
    assert (policy.act(obs, deterministic=True).actions - demos).abs().max() < 0.1
    # the mask drops samples: only masked-in rows count
    half = torch.tensor([True, False] * 32)
    torch.manual_seed(3)
    masked = policy.bc_loss(batch, targets, mask=half)
    assert torch.isfinite(masked) and masked.item() >= 0


def test_policy_gradient_through_the_denoising_path_moves_the_action():
    """A REINFORCE loop on evaluate()'s log-probs (what PPO/GRPO do) pulls the ODE action to a target."""
    torch.manual_seed(0)
    policy = flow_policy(action_dim=2, chunk=1, obs_dim=3, num_steps=5, noise_level=0.7, value_head=False)
    obs = state_obs(batch=1)
    batch = {"state": obs["state"].expand(64, 3)}
    target = torch.tensor([0.8, -0.6])

    def distance():
        with torch.no_grad():
            return (policy.act(obs, deterministic=True).actions[0, 0] - target).norm().item()

    before = distance()
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    for _ in range(60):
        with torch.no_grad():
            step = policy.act(batch)
        reward = -((step.actions[:, 0] - target) ** 2).sum(-1)
        advantage = (reward - reward.mean()) / (reward.std() + 1e-6)
        logprobs = policy.evaluate(batch, step.actions, step.extras, with_entropy=False).logprobs[:, 0]
        loss = -(advantage * logprobs).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert distance() < 0.5 * before
