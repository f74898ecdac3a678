"""π0 / π0.5 as RL policies: flow-SDE log-probs of the denoising chain, and the ODE path is
LeRobot's own sampler (checked against the reference chunk)."""

import math

import pytest
import torch

from infinirl.models.policies.base import build_policy
from infinirl.models.policies.flow import flow_sde_sigmas, flow_timesteps
from tests.unit.models.vla_fixtures import FAMILIES, FIXTURES, TOKENIZER, raw_observation, reference

CAMERAS = {"rgb": "observation.images.base_0_rgb", "wrist_rgb": "observation.images.left_wrist_0_rgb"}


def policy(family, **kwargs):
    options = dict(checkpoint=str(FIXTURES / family), architecture=str(FIXTURES / "architecture.json"),
                   tokenizer=str(TOKENIZER), action_dim=3, chunk=2, cameras=CAMERAS, value_hidden=16)
    options.update(kwargs)
    return build_policy(family, **options)


def env_obs(family):
    """The reference's raw inputs under env keys (float CHW images are accepted as well as uint8 HWC)."""
    raw = raw_observation(family)
    return {"rgb": raw["observation.images.base_0_rgb"], "wrist_rgb": raw["observation.images.left_wrist_0_rgb"],
            "state": raw["observation.state"], "instruction": raw["task"]}


@pytest.fixture(scope="module", params=FAMILIES)
def case(request):
    torch.manual_seed(0)
    return request.param, policy(request.param)


def test_ode_path_is_the_reference_sampler(case):
    family, pi = case
    ref = reference(family)
    chain, _, _, _ = pi.denoise(pi.inputs(env_obs(family)), ref["noise"], deterministic=True)
    error = (chain[:, -1] - ref["sampled_normalized"]).abs().max().item()
    assert error <= 1e-5 * max(ref["sampled_normalized"].abs().max().item(), 1.0)


def reference_logprob(pi, obs, chain, mask):
    """Float64 loop: each step's Gaussian written out (Flow-GRPO's SDE step in tau = 1 - t, with
    velocity -v_pi0), summed over the executed rows/dims and the stochastic steps."""
    inputs = pi.inputs(obs)
    prefix = pi.vla.model.encode_prefix(inputs.images, inputs.image_masks, inputs.tokens, inputs.token_mask)
    steps = pi.num_steps
    taus = flow_timesteps(steps, torch.float64)
    sigmas = flow_sde_sigmas(taus, pi.noise_level)
    total = torch.zeros(chain.shape[0], pi.chunk, dtype=torch.float64)
    for k in range(steps):
        x = chain[:, k].double()
        t = torch.full((x.shape[0],), 1.0 - k / steps)
        v = -pi.vla.model.velocity(prefix, inputs.state, x.float(), t).double()
        tau, dtau, sigma = taus[k].item(), 1.0 / steps, sigmas[k].item()
        mean = x + v * dtau - sigma**2 * dtau / (2 * (1 - tau)) * (x - tau * v)
        std = sigma * math.sqrt(dtau)
        logp = torch.distributions.Normal(mean, std).log_prob(chain[:, k + 1].double())
        total += logp[:, :pi.chunk, :pi.action_dim].sum(-1) * mask[:, k, None]
    return total


def test_act_logprobs_match_evaluate_and_a_float64_loop(case):
    family, pi = case
    obs = env_obs(family)
    torch.manual_seed(1)
    step = pi.act(obs)
    assert step.actions.shape == (2, 2, 3) and step.logprobs.shape == (2, 2) and step.values.shape == (2,)
    assert step.extras["chain"].shape == (2, pi.num_steps + 1, 4, 8)
    evaluated = pi.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, atol=1e-4, rtol=1e-5)
    with torch.no_grad():
        expected = reference_logprob(pi, obs, step.extras["chain"], step.extras["sde_mask"])
    torch.testing.assert_close(evaluated.logprobs.double(), expected, atol=1e-3, rtol=1e-5)
    assert evaluated.entropy.shape == (2, 2) and evaluated.values.shape == (2,)


def test_actions_are_the_chain_end_in_env_units(case):
    family, pi = case
    torch.manual_seed(2)
    step = pi.act(env_obs(family), deterministic=True)
    expected = pi.vla.processor.actions_out(step.extras["chain"][:, -1])[:, :2, :3]
    torch.testing.assert_close(step.actions, expected)


def test_evaluate_is_differentiable(case):
    family, pi = case
    obs = env_obs(family)
    torch.manual_seed(3)
    step = pi.act(obs)
    pi.zero_grad()
    evaluated = pi.evaluate(obs, step.actions, step.extras)
    (evaluated.logprobs.sum() + evaluated.values.sum()).backward()
    model = pi.vla.model
    for name, module in (("expert", model.expert), ("vlm", model.vlm), ("critic", pi.value_net)):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.parameters()), name
    pi.zero_grad()



def test_detached_critic_trains_the_value_head_only():
    pi = policy("pi0", detach_critic=True)
    obs = env_obs("pi0")
    torch.manual_seed(3)
    step = pi.act(obs)
    pi.zero_grad()
    pi.evaluate(obs, step.actions, step.extras).values.sum().backward()
    model = pi.vla.model
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in pi.value_net.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.parameters())
    pi.zero_grad()

@pytest.mark.parametrize("family", FAMILIES)
def test_expert_critic_reads_the_action_experts_output_at_the_noises_mean(family):
    """``critic_input="expert"`` (pi_RL's π0 critic): the value head on the expert's outputs at the
    executed action tokens, averaged, from one pass at time 1 with zero noise: the same value for
    every noise draw, in act, evaluate (all steps and one step) and value; gradients reach the
    expert, and with ``detach_critic`` the value head only."""
    pi = policy(family, critic_input="expert")
    obs = env_obs(family)
    x = pi.inputs(obs)
    prefix = pi._prefix(x)
    config = pi.vla.config
    zero = torch.zeros(2, config.chunk_size, config.max_action_dim)
    _, hidden = pi.vla.model.velocity(prefix, x.state, zero, torch.ones(2), return_hidden=True)
    expected = pi.value_net(hidden[:, :pi.chunk].mean(1)).squeeze(-1)
    torch.manual_seed(3)
    first, second = pi.act(obs), pi.act(obs)
    assert not torch.equal(first.actions, second.actions)
    for values in (first.values, second.values, pi.value(obs), pi.evaluate(obs, first.actions, first.extras).values):
        torch.testing.assert_close(values, expected, rtol=1e-5, atol=1e-6)
    one = policy(family, critic_input="expert", sde_steps="one")
    step = one.act(obs)
    torch.testing.assert_close(one.evaluate(obs, step.actions, step.extras).values, step.values, rtol=1e-5, atol=1e-6)
    for detach in (False, True):
        critic = policy(family, critic_input="expert", detach_critic=detach)
        critic.value(obs).sum().backward()
        expert_grad = sum(float(p.grad.abs().sum()) for p in critic.vla.model.expert.parameters() if p.grad is not None)
        assert (expert_grad == 0.0) == detach
        assert all(p.grad is not None for p in critic.value_net.parameters())
    with pytest.raises(ValueError, match="critic_input must be one of"):
        policy(family, critic_input="vlm")


def test_one_stochastic_step():
    pi = policy("pi0", sde_steps="one", value_head=False)
    obs = env_obs("pi0")
    torch.manual_seed(4)
    step = pi.act(obs)
    assert step.values is None and step.extras["sde_mask"].sum(1).tolist() == [1, 1]
    evaluated = pi.evaluate(obs, step.actions, step.extras, with_entropy=True)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, atol=1e-4, rtol=1e-5)
    with torch.no_grad():
        expected = reference_logprob(pi, obs, step.extras["chain"], step.extras["sde_mask"])
    torch.testing.assert_close(evaluated.logprobs.double(), expected, atol=1e-3, rtol=1e-5)
    # rows at different steps, evaluated in one pass, against the every-step loop of the same chains
    mask = torch.nn.functional.one_hot(torch.tensor([0, pi.num_steps - 1]), pi.num_steps).bool()
    chain = pi.denoise(pi.inputs(obs), torch.randn_like(step.extras["chain"][:, 0]), mask=mask)[0]
    fast = pi.evaluate(obs, step.actions, {"chain": chain, "sde_mask": mask})
    torch.testing.assert_close(fast.logprobs.double(),
                               reference_logprob(pi, obs, chain, mask), atol=1e-3, rtol=1e-5)
    timesteps = flow_timesteps(pi.num_steps, torch.float64)
    stds = flow_sde_sigmas(timesteps, pi.noise_level) * (timesteps[1:] - timesteps[:-1]).sqrt()
    entropy = pi.action_dim * (0.5 * math.log(2 * math.pi * math.e) + stds[[0, pi.num_steps - 1]].log())
    torch.testing.assert_close(fast.entropy.double(), entropy[:, None].expand(2, pi.chunk), atol=1e-5, rtol=1e-5)


def test_checkpoint_and_env_must_agree():
    with pytest.raises(ValueError, match="'pi0' checkpoint, not 'pi05'"):
        policy("pi05", checkpoint=str(FIXTURES / "pi0"))
    with pytest.raises(ValueError, match="chunks of 5 x 3"):
        policy("pi0", chunk=5)
    with pytest.raises(ValueError, match="does not have"):
        policy("pi0", cameras={"rgb": "observation.images.top"})


def test_env_state_of_another_width_is_refused(case):
    family, pi = case
    obs = env_obs(family)
    obs["state"] = torch.zeros(2, 9)
    with pytest.raises(ValueError, match=r"expects \[B, 5\]"):
        pi.act(obs)


def reference_fpo_scores(pi, obs, extras):
    """Float64: each recorded (time, noise) draw's flow-matching loss through the model's own
    training loss (prefix and suffix in one joint pass, no cache), summed over the executed
    rows/dims, averaged over the draws, negated."""
    model = pi.vla.model.double()
    try:
        inputs = pi.inputs(obs)
        images = [image.double() for image in inputs.images]
        state = None if inputs.state is None else inputs.state.double()
        action = extras["fpo_action"].double()
        total = torch.zeros(action.shape[0], pi.chunk, dtype=torch.float64)
        samples = extras["fpo_time"].shape[1]
        for n in range(samples):
            errors = model.loss_elements(images, inputs.image_masks, inputs.tokens, inputs.token_mask, state,
                                         action, noise=extras["fpo_noise"][:, n].double(),
                                         time=extras["fpo_time"][:, n].double())
            total += errors.double()[:, :pi.chunk, :pi.action_dim].sum(-1) / samples
        return -total
    finally:
        model.float()


def test_fpo_scores_are_minus_the_flow_matching_loss(case):
    family, _ = case
    torch.manual_seed(5)
    pi = policy(family, likelihood="fpo", fpo_samples=3)
    obs = env_obs(family)
    step = pi.act(obs)
    assert step.extras["fpo_noise"].shape == (2, 3, 4, 8) and step.extras["fpo_time"].shape == (2, 3)
    # the action is the ODE sampler's from some noise: the chunk the policy is evaluated with
    expected_actions = pi.vla.processor.actions_out(step.extras["fpo_action"])[:, :2, :3]
    torch.testing.assert_close(step.actions, expected_actions)
    evaluated = pi.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, atol=1e-5, rtol=1e-5)
    with torch.no_grad():
        expected = reference_fpo_scores(pi, obs, step.extras)
    torch.testing.assert_close(evaluated.logprobs.double(), expected, atol=1e-4, rtol=1e-4)
    assert evaluated.entropy is None and evaluated.values.shape == (2,)
    (evaluated.logprobs.sum() + evaluated.values.sum()).backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in pi.vla.model.expert.parameters())


def test_fpo_needs_its_draws_and_a_known_likelihood():
    pi = policy("pi0", likelihood="fpo")
    obs = env_obs("pi0")
    with pytest.raises(ValueError, match=r"needs extras \['fpo_action', 'fpo_noise', 'fpo_time'\]"):
        pi.evaluate(obs, torch.zeros(2, 2, 3), {"chain": torch.zeros(2, 3)})
    with pytest.raises(ValueError, match="likelihood must be one of"):
        policy("pi0", likelihood="elbo")


def reference_flow_noise_logprob(pi, obs, chain, mask):
    """Float64 loop: each step's Gaussian written out with the Euler step as its mean and the noise
    head's squashed output as its std, summed over the executed rows/dims and the stochastic steps."""
    inputs = pi.inputs(obs)
    prefix = pi.vla.model.encode_prefix(inputs.images, inputs.image_masks, inputs.tokens, inputs.token_mask)
    steps = pi.num_steps
    weight, bias = pi.std_net.weight.double(), pi.std_net.bias.double()
    total = torch.zeros(chain.shape[0], pi.chunk, dtype=torch.float64)
    for k in range(steps):
        x = chain[:, k].double()
        t = torch.full((x.shape[0],), 1.0 - k / steps)
        v_pi0, hidden = pi.vla.model.velocity(prefix, inputs.state, x.float(), t, return_hidden=True)
        mean = x - v_pi0.double() / steps
        std = pi.min_std + (pi.max_std - pi.min_std) / (1 + torch.exp(-(hidden.double() @ weight.T + bias)))
        logp = torch.distributions.Normal(mean, std).log_prob(chain[:, k + 1].double())
        total += logp[:, :pi.chunk, :pi.action_dim].sum(-1) * mask[:, k, None]
    return total


def flow_noise_policy(family, **kwargs):
    torch.manual_seed(6)
    pi = policy(family, likelihood="flow_noise", min_std=0.05, max_std=0.3, **kwargs)
    with torch.no_grad():  # a trained head: stds that vary by element, not the initial middle
        pi.std_net.weight.normal_(0.0, 0.5)
        pi.std_net.bias.normal_(0.0, 0.5)
    return pi


def test_flow_noise_logprobs_match_evaluate_and_a_float64_loop(case):
    family, _ = case
    pi = flow_noise_policy(family)
    obs = env_obs(family)
    torch.manual_seed(7)
    step = pi.act(obs)
    evaluated = pi.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, atol=1e-4, rtol=1e-5)
    with torch.no_grad():
        expected = reference_flow_noise_logprob(pi, obs, step.extras["chain"], step.extras["sde_mask"])
    torch.testing.assert_close(evaluated.logprobs.double(), expected, atol=1e-3, rtol=1e-5)
    # the learned std is trained by the log-probs (and the entropy), with the expert below it
    pi.zero_grad()
    (evaluated.logprobs.sum() + evaluated.entropy.sum()).backward()
    assert pi.std_net.weight.grad.abs().sum() > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in pi.vla.model.expert.parameters())
    # one stochastic step a row: the one-pass evaluation gives the same densities
    mask = torch.nn.functional.one_hot(torch.tensor([1, pi.num_steps - 1]), pi.num_steps).bool()
    chain = pi.denoise(pi.inputs(obs), torch.randn_like(step.extras["chain"][:, 0]), mask=mask)[0]
    fast = pi.evaluate(obs, step.actions, {"chain": chain, "sde_mask": mask})
    with torch.no_grad():
        torch.testing.assert_close(fast.logprobs.double(), reference_flow_noise_logprob(pi, obs, chain, mask),
                                   atol=1e-3, rtol=1e-5)


def test_flow_noise_acts_deterministically_with_the_ode_and_starts_mid_range():
    obs = env_obs("pi0")
    noise_policy = policy("pi0", likelihood="flow_noise", min_std=0.05, max_std=0.3)
    plain = policy("pi0")
    plain.load_state_dict(noise_policy.state_dict(), strict=False)
    inputs = noise_policy.inputs(obs)
    noise = torch.randn(2, 4, 8)
    ode_chain = noise_policy.denoise(inputs, noise, deterministic=True)[0]
    torch.testing.assert_close(ode_chain, plain.denoise(plain.inputs(obs), noise, deterministic=True)[0])
    prefix = noise_policy._prefix(inputs)
    _, std, _ = noise_policy.transition(prefix, inputs.state, noise, 0)
    torch.testing.assert_close(std, torch.full_like(std, 0.175))
    assert noise_policy.fresh_modules == ("std_net",) and plain.std_net is None


def test_flow_noise_std_range_is_checked():
    with pytest.raises(ValueError, match="flow_noise needs 0 < min_std < max_std, got min_std=0.2, max_std=0.1"):
        policy("pi0", likelihood="flow_noise", min_std=0.2, max_std=0.1)
