"""Policies (MLP Gaussian, CNN Gaussian, CNN bins) against slow float64 references written as loops.

The flow-matching policy has its own file, ``test_policies_flow.py``.
"""

import math

import pytest
import torch
from torch.distributions import Categorical, Normal

from infinirl.models.policies.base import POLICIES, PolicyStep, build_policy, prepare_obs
from infinirl.models.policies.heads import ConvEncoder

SMALL_CNN = dict(channels=(8, 16, 16), features=32, hidden=(32,), value_hidden=(32,))


def state_obs(batch=5, dim=4, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return {"state": torch.randn(batch, dim, generator=generator)}


def pixel_obs(batch=4, shape=(64, 64, 3), proprio=3, seed=0):
    generator = torch.Generator().manual_seed(seed)
    obs = {"rgb": torch.randint(0, 256, (batch, *shape), dtype=torch.uint8, generator=generator)}
    if proprio:
        obs["proprio"] = torch.randn(batch, proprio, generator=generator)
    return obs


def all_params_get_gradient(policy, obs, step: PolicyStep):
    policy.zero_grad()
    evaluation = policy.evaluate(obs, step.actions, step.extras)
    loss = evaluation.logprobs.sum() + evaluation.values.sum()
    if evaluation.entropy is not None:
        loss = loss + evaluation.entropy.sum()
    loss.backward()
    missing = [name for name, p in policy.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing, f"no gradient reached {missing}"


def test_registered_names_and_build():
    build_policy("mlp_gaussian", obs_dim=3, action_dim=2)
    for name in ("mlp_gaussian", "cnn_gaussian", "cnn_bins", "flow_matching"):
        assert POLICIES.get(name) is not None


def test_switches_must_be_booleans():
    """An option declared ``bool`` (here the base class's ``value_head``, and a mixin's along the
    MRO for the VLA forms) refuses a string a config override left unparsed."""
    with pytest.raises(ValueError, match="^value_head must be true or false, got 'maybe'$"):
        build_policy("mlp_gaussian", obs_dim=3, action_dim=2, value_head="maybe")
    with pytest.raises(ValueError, match="^residual_pixels must be true or false, got 1$"):
        build_policy("pi0_smollm2_residual", checkpoint="unused", action_dim=4, residual_pixels=1)


# --- MLP Gaussian ----------------------------------------------------------------------------


def gaussian_reference(mean, log_std, actions):
    """Loop over (sample, chunk step, dim) with torch.distributions.Normal, in float64."""
    batch, chunk, dims = actions.shape
    logp = torch.zeros(batch, chunk, dtype=torch.float64)
    entropy = torch.zeros(batch, chunk, dtype=torch.float64)
    for b in range(batch):
        for k in range(chunk):
            for d in range(dims):
                dist = Normal(mean[b, k, d].double(), log_std[b, k, d].double().exp())
                logp[b, k] += dist.log_prob(actions[b, k, d].double())
                entropy[b, k] += dist.entropy()
    return logp, entropy


@pytest.mark.parametrize("chunk", [1, 3])
def test_mlp_logprob_and_entropy_match_normal_loop(chunk):
    torch.manual_seed(0)
    policy = build_policy("mlp_gaussian", obs_dim=4, action_dim=2, chunk=chunk, init_log_std=-0.5).double()
    with torch.no_grad():
        policy.log_std.copy_(torch.linspace(-1.0, 0.5, 2 * chunk))
    obs = state_obs()  # float32 observations into a float64 policy: cast inside
    step = policy.act(obs)
    assert step.actions.shape == (5, chunk, 2) and step.logprobs.shape == (5, chunk)
    assert step.values.shape == (5,) and step.actions.dtype == torch.float64
    evaluation = policy.evaluate(obs, step.actions)
    mean = policy._mean(obs).view(5, chunk, 2)
    log_std = policy.log_std.view(1, chunk, 2).expand(5, chunk, 2)
    ref_logp, ref_entropy = gaussian_reference(mean, log_std, step.actions)
    torch.testing.assert_close(step.logprobs, ref_logp, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(evaluation.logprobs, ref_logp, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(evaluation.entropy, ref_entropy, rtol=1e-12, atol=1e-12)


def test_mlp_deterministic_gradients_and_prepare_obs():
    torch.manual_seed(0)
    policy = build_policy("mlp_gaussian", obs_dim=4, action_dim=2, chunk=2)
    obs = prepare_obs({"state": state_obs()["state"].numpy()})
    first, second = policy.act(obs, deterministic=True), policy.act(obs, deterministic=True)
    torch.testing.assert_close(first.actions, second.actions, rtol=0, atol=0)
    torch.testing.assert_close(first.actions, policy._mean(obs).view(5, 2, 2))
    sampled = policy.act(obs)
    assert not torch.allclose(sampled.actions, first.actions)
    all_params_get_gradient(policy, obs, sampled)


def test_mlp_learns_target_action():
    torch.manual_seed(0)
    policy = build_policy("mlp_gaussian", obs_dim=4, action_dim=2, chunk=2)
    obs = state_obs(batch=8)
    target = torch.tensor([[0.5, -0.3], [0.2, 0.7]]).expand(8, 2, 2)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-2)
    before = (policy.act(obs, deterministic=True).actions - target).abs().max()
    for _ in range(200):
        loss = -policy.evaluate(obs, target, with_entropy=False).logprobs.mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert before > 0.5
    assert (policy.act(obs, deterministic=True).actions - target).abs().max() < 0.1


# --- CNN Gaussian ----------------------------------------------------------------------------


@pytest.mark.parametrize("state_dependent_std", [False, True])
def test_cnn_gaussian_logprob_and_entropy_match_normal_loop(state_dependent_std):
    torch.manual_seed(0)
    policy = build_policy("cnn_gaussian", action_dim=2, chunk=3, proprio_dim=3, init_log_std=-0.7,
                          state_dependent_std=state_dependent_std, **SMALL_CNN).double()
    obs = pixel_obs()
    step = policy.act(obs)
    assert step.actions.shape == (4, 3, 2) and step.logprobs.shape == (4, 3) and step.values.shape == (4,)
    assert step.extras == {}
    evaluation = policy.evaluate(obs, step.actions)
    mean, log_std = policy.head(policy.encoder(obs))
    ref_logp, ref_entropy = gaussian_reference(mean.view(4, 3, 2), log_std.view(4, 3, 2), step.actions)
    torch.testing.assert_close(step.logprobs, ref_logp, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(evaluation.logprobs, ref_logp, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(evaluation.entropy, ref_entropy, rtol=1e-12, atol=1e-12)
    # starts at init_log_std either way (the state-dependent one through its bias)
    torch.testing.assert_close(log_std, torch.full_like(log_std, -0.7), rtol=0, atol=0.05)
    if state_dependent_std:
        assert log_std.std() > 0  # depends on the observation
        assert (log_std >= -5).all() and (log_std <= 2).all()


@pytest.mark.parametrize("separate_critic", [False, True])
def test_cnn_gaussian_deterministic_and_gradients(separate_critic):
    torch.manual_seed(0)
    policy = build_policy("cnn_gaussian", action_dim=2, chunk=2, proprio_dim=3,
                          separate_critic=separate_critic, state_dependent_std=True, **SMALL_CNN)
    obs = pixel_obs()
    first, second = policy.act(obs, deterministic=True), policy.act(obs, deterministic=True)
    torch.testing.assert_close(first.actions, second.actions, rtol=0, atol=0)
    torch.testing.assert_close(policy.value(obs), first.values)
    all_params_get_gradient(policy, obs, policy.act(obs))
    assert (policy.critic_encoder is not None) == separate_critic


def test_conv_encoder_normalises_uint8_and_checks_shape():
    torch.manual_seed(0)
    encoder = ConvEncoder((84, 84, 3), channels=(8, 16, 16), features=16)
    image = torch.randint(0, 256, (2, 84, 84, 3), dtype=torch.uint8)
    torch.testing.assert_close(encoder(image), encoder(image.float() / 255))
    with pytest.raises(ValueError, match=r"\[B, 84, 84, 3\]"):
        encoder(torch.zeros(2, 64, 64, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="too small"):
        ConvEncoder((16, 16, 3))


def test_cnn_policy_without_value_head():
    policy = build_policy("cnn_gaussian", action_dim=2, value_head=False, **SMALL_CNN)
    obs = pixel_obs(proprio=0)
    assert policy.act(obs).values is None and not policy.has_value_head
    with pytest.raises(NotImplementedError):
        policy.value(obs)


def test_cnn_gaussian_learns_target_action():
    torch.manual_seed(0)
    policy = build_policy("cnn_gaussian", action_dim=2, chunk=2, proprio_dim=3, **SMALL_CNN)
    obs = pixel_obs(batch=2)
    target = torch.tensor([[0.5, -0.3], [0.2, 0.7]]).expand(2, 2, 2)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-2)
    for _ in range(60):
        loss = -policy.evaluate(obs, target, with_entropy=False).logprobs.mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert (policy.act(obs, deterministic=True).actions - target).abs().max() < 0.05


# --- CNN bins --------------------------------------------------------------------------------

LOW, HIGH = [-1.0, 0.0, -2.0], [1.0, 0.5, 2.0]


def bins_policy(num_bins=7, chunk=2, **kwargs):
    return build_policy("cnn_bins", action_dim=3, chunk=chunk, proprio_dim=3, num_bins=num_bins, low=LOW,
                        high=HIGH, **SMALL_CNN, **kwargs)


def test_bins_logprob_and_entropy_match_loop_over_dims():
    torch.manual_seed(0)
    policy = bins_policy().double()
    with torch.no_grad():  # make the categoricals far from uniform
        policy.head.net[-1].weight.mul_(300)
    obs = pixel_obs()
    step = policy.act(obs)
    evaluation = policy.evaluate(obs, step.actions)
    logits = policy.head.net(policy.encoder(obs)).view(4, 2, 3, 7)
    ref_logp = torch.zeros(4, 2, dtype=torch.float64)
    ref_entropy = torch.zeros(4, 2, dtype=torch.float64)
    for b in range(4):
        for k in range(2):
            for d in range(3):
                width = (HIGH[d] - LOW[d]) / 7
                index = int(math.floor((step.actions[b, k, d].item() - LOW[d]) / width))
                dist = Categorical(logits=logits[b, k, d])
                ref_logp[b, k] += dist.log_prob(torch.tensor(index))
                ref_entropy[b, k] += dist.entropy()
    assert ref_entropy.min() < 3 * math.log(7) - 0.5  # not uniform, so the check has teeth
    torch.testing.assert_close(step.logprobs, ref_logp, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(evaluation.logprobs, ref_logp, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(evaluation.entropy, ref_entropy, rtol=1e-12, atol=1e-12)


def test_bins_actions_are_bin_centres_inside_the_box():
    torch.manual_seed(0)
    policy = bins_policy(num_bins=5, chunk=3)
    obs = pixel_obs(batch=16)
    for deterministic in (False, True):
        actions = policy.act(obs, deterministic=deterministic).actions
        assert actions.shape == (16, 3, 3)
        for d in range(3):
            width = (HIGH[d] - LOW[d]) / 5
            centres = torch.tensor([LOW[d] + (i + 0.5) * width for i in range(5)])
            distance = (actions[..., d, None] - centres).abs().min(-1).values
            assert distance.max() < 1e-6
            assert (actions[..., d] > LOW[d]).all() and (actions[..., d] < HIGH[d]).all()
    # out-of-box actions score as the edge bins; deterministic = argmax
    head = policy.head
    index = head.to_index(torch.tensor([[[-5.0, 9.0, 2.0]]]))
    assert index.tolist() == [[[0, 4, 4]]]
    features = policy.encoder(obs)
    greedy = policy.act(obs, deterministic=True)
    torch.testing.assert_close(greedy.actions, head.to_action(head(features).argmax(-1)))


def test_bins_sampling_follows_the_categorical():
    torch.manual_seed(0)
    policy = build_policy("cnn_bins", action_dim=1, num_bins=4, low=0.0, high=4.0, **SMALL_CNN)
    with torch.no_grad():
        policy.head.net[-1].weight.zero_()
        policy.head.net[-1].bias.copy_(torch.log(torch.tensor([0.1, 0.2, 0.3, 0.4])))
    obs = pixel_obs(batch=4000, proprio=0, shape=(64, 64, 3))
    obs["rgb"] = obs["rgb"][:1].expand(4000, 64, 64, 3)
    with torch.no_grad():
        actions = policy.act(obs).actions.flatten()
    frequencies = torch.stack([(actions == c).float().mean() for c in (0.5, 1.5, 2.5, 3.5)])
    torch.testing.assert_close(frequencies, torch.tensor([0.1, 0.2, 0.3, 0.4]), rtol=0, atol=0.03)


def test_bins_gradients_and_learning():
    torch.manual_seed(0)
    policy = bins_policy(num_bins=9)
    obs = pixel_obs()
    all_params_get_gradient(policy, obs, policy.act(obs))
    centres = policy.head.centres  # [A, bins]
    target = torch.stack([centres[0, 2], centres[1, 7], centres[2, 4]]).expand(4, 2, 3)
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    for _ in range(60):
        loss = -policy.evaluate(obs, target, with_entropy=False).logprobs.mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    torch.testing.assert_close(policy.act(obs, deterministic=True).actions, target)


def test_bins_rejects_bad_boxes():
    with pytest.raises(ValueError, match="high must exceed"):
        build_policy("cnn_bins", action_dim=2, low=[0.0, 1.0], high=[1.0, 1.0], **SMALL_CNN)
    with pytest.raises(ValueError, match="2 numbers"):
        build_policy("cnn_bins", action_dim=2, low=[0.0, 0.0, 0.0], **SMALL_CNN)
