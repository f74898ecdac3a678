"""The residual VLA (``pi0_smollm2_residual``, :mod:`infinirl.models.vla.residual`): RL adds a small
Gaussian policy's chunk to the frozen VLA's noise-free chunk. At the start its noise-free action is
the VLA's from noise 0; its log-probs are the residual's Gaussian density per action (float64
reference), recomputed by the trainer from the batch alone; only the two small networks train; PPO
moves its noise-free action toward a rewarded one outside what the VLA produces."""

import pytest
import torch

from infinirl.components.embodied_policy import NormalizedPolicy
from tests.unit.models.test_vla_steered import BATCH, observations, ppo_on_a_bandit, tiny_checkpoint
from tests.unit.models.test_vla_steered import policy as steered_or_plain

# two VLA passes on the same inputs may run different oneDNN kernels (seen on a loaded CPU), which differ in
# the last float32 bits of the actions (O(1) in size): "starts as the VLA" is checked to 1e-4
START_ATOL = 1e-4


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory)


def policy(checkpoint, name="pi0_smollm2_residual", **options):
    return steered_or_plain(checkpoint, name=name, **options)


def test_at_the_start_its_noise_free_action_is_the_vlas_from_noise_zero(checkpoint, monkeypatch):
    residual, plain = policy(checkpoint, residual_std=0.3), policy(checkpoint, name="pi0_smollm2")
    obs = observations()
    noise_free = residual.act(obs, deterministic=True)
    with monkeypatch.context() as patch:
        patch.setattr(torch, "randn", lambda *shape, device=None, **kwargs: torch.zeros(*shape, device=device))
        reference = plain.act(obs, deterministic=True)
    torch.testing.assert_close(noise_free.actions, reference.actions, rtol=0, atol=START_ATOL)
    assert torch.equal(noise_free.extras["residual"], torch.zeros_like(noise_free.extras["residual"]))
    torch.manual_seed(3)
    sampled = residual.act(obs)
    torch.testing.assert_close(sampled.actions - noise_free.actions, sampled.extras["residual"], rtol=0,
                               atol=START_ATOL)
    assert 0.25 < float(sampled.extras["residual"].std()) < 0.35


def test_logprobs_are_the_residuals_density_and_the_trainer_recomputes_them_from_the_batch(checkpoint, monkeypatch):
    residual = policy(checkpoint)
    with torch.no_grad():
        residual.residual_net[-1].bias.normal_(0.0, 0.5)  # a mean away from 0
        residual.residual_log_std.normal_(-1.5, 0.2)
    step = residual.act(observations())
    assert step.logprobs.shape == (BATCH, 2) and step.actions.shape == (BATCH, 2, 4)
    taken, inputs = step.extras["residual"].double(), step.extras["features"].double()
    raw = residual.residual_net.double()(inputs).reshape(BATCH, 2, 4)
    mean = residual.residual_bound * torch.tanh(raw / residual.residual_bound)
    std = residual.residual_log_std.double().exp()
    normal = torch.distributions.Normal(mean, std)
    torch.testing.assert_close(step.logprobs.double(), normal.log_prob(taken).sum(-1), rtol=1e-5, atol=1e-4)
    residual.float()

    def no_vla(*args, **kwargs):
        raise AssertionError("evaluate ran the VLA")

    monkeypatch.setattr(residual.vla.model, "encode_prefix", no_vla)
    evaluated = residual.evaluate({}, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, rtol=0, atol=1e-5)
    torch.testing.assert_close(evaluated.entropy.double(), normal.entropy().sum(-1), rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(evaluated.values, step.values, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match=r"needs extras\['residual'\]"):
        residual.evaluate({}, step.actions, {"features": step.extras["features"]})


def test_with_pixels_cnns_of_their_own_read_the_frames_and_train(checkpoint):
    """``residual_pixels``: the residual policy and the critic each read the camera frame through a
    CNN of their own (the critic's trains at the value rate); the start is still the VLA's
    noise-free action, evaluate recomputes the log-probs from the batch's frames with gradients
    into the policy's CNN, and a batch without the frames is named."""
    residual, plain = policy(checkpoint, residual_pixels=True), policy(checkpoint)
    obs = observations()
    torch.testing.assert_close(residual.act(obs, deterministic=True).actions,
                               plain.act(obs, deterministic=True).actions, rtol=0, atol=START_ATOL)
    with torch.no_grad():
        residual.residual_net[-1].weight.normal_(0.0, 0.1)  # the frames now move the mean
    step = residual.act(obs)
    evaluated = residual.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, rtol=0, atol=1e-5)
    torch.testing.assert_close(evaluated.values, step.values, rtol=0, atol=1e-6)
    (evaluated.logprobs.sum() + evaluated.values.sum()).backward()
    for encoder in (residual.residual_encoder, residual.value_encoder):
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in encoder.parameters())
    assert residual.critic_modules == ("value_net", "value_encoder")
    shifted = {**obs, "rgb": torch.roll(obs["rgb"], 3, dims=1)}
    assert not torch.allclose(residual.evaluate(shifted, step.actions, step.extras).logprobs, step.logprobs)
    with pytest.raises(ValueError, match="reads the observation's 'rgb' frames, which it lacks"):
        residual.evaluate({}, step.actions, step.extras)


def test_input_norm_standardises_with_the_first_training_batch_then_keeps_it(checkpoint):
    """``residual_input_norm``: until the trainer fits it the inputs pass unchanged (the zero output
    layer makes the start the VLA's either way); the first batch's ``extras['features']`` set the
    per-dimension mean and std (float64 reference), later batches do not move them, the statistics
    are buffers (saved and synced with the weights), and the MLPs read the standardised inputs."""
    residual, plain = policy(checkpoint, residual_input_norm=True), policy(checkpoint)
    obs = observations()
    first = residual.act(obs)
    torch.testing.assert_close(residual.act(obs, deterministic=True).actions,
                               plain.act(obs, deterministic=True).actions, rtol=0, atol=START_ATOL)
    model = NormalizedPolicy(residual, {}, 10.0)
    model.fit_input_stats(first.extras)
    features = first.extras["features"].double()
    torch.testing.assert_close(residual.input_rms.mean, features.mean(0), rtol=0, atol=1e-9)
    torch.testing.assert_close(residual.input_rms.var, features.var(0, unbiased=False), rtol=1e-6, atol=1e-9)
    model.fit_input_stats({"features": first.extras["features"] + 5.0})
    torch.testing.assert_close(residual.input_rms.mean, features.mean(0), rtol=0, atol=1e-9)
    assert {"input_rms.mean", "input_rms.var", "input_rms.count"} <= set(residual.state_dict())
    torch.testing.assert_close(residual.act(obs, deterministic=True).actions,
                               plain.act(obs, deterministic=True).actions, rtol=0, atol=START_ATOL)

    with torch.no_grad():
        residual.residual_net[-1].weight.normal_(0.0, 0.1)
    step = residual.act(obs)
    standardised = ((features - features.mean(0)) / (features.var(0, unbiased=False) + 1e-8).sqrt()).clamp(-10, 10)
    raw = residual.residual_net.double()(standardised).reshape(BATCH, 2, 4)
    residual.float()
    mean = residual.residual_bound * torch.tanh(raw / residual.residual_bound)
    normal = torch.distributions.Normal(mean, residual.residual_log_std.double().exp())
    torch.testing.assert_close(step.logprobs.double(), normal.log_prob(step.extras["residual"].double()).sum(-1),
                               rtol=1e-5, atol=1e-4)
    evaluated = residual.evaluate({}, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, rtol=0, atol=1e-5)

    unfitted = policy(checkpoint, residual_input_norm=True)
    with pytest.raises(ValueError, match=r"residual_input_norm fits its statistics on extras\['features'\]"):
        unfitted.fit_input_stats({"residual": first.extras["residual"]})
    NormalizedPolicy(plain, {}, 10.0).fit_input_stats(first.extras)  # a policy without input statistics: no-op
    assert plain.input_rms is None


def test_held_noise_is_the_gsde_draw_of_its_seed_and_keeps_the_residuals_density(checkpoint):
    """``held_noise`` beta: the sampled residual is ``mu + sigma * (sqrt(1 - beta) * xi + sqrt(beta)
    * z . w)``, ``z`` the residual network's unit-length last hidden layer and ``w`` drawn from the
    seed the rollout gives (float64 reference); the same seed holds the same draw, a new one
    redraws, and the log-probs stay the ``N(mu, sigma^2)`` density of what was taken."""
    residual = policy(checkpoint, held_noise=0.36, held_noise_every=3)
    assert residual.held_noise_every == 3 and policy(checkpoint).held_noise_every == 0
    with torch.no_grad():
        residual.residual_net[-1].weight.normal_(0.0, 0.1)
        residual.residual_log_std.normal_(-1.0, 0.2)
    obs = observations()
    residual.held_noise = 0.0  # the same call without the held part gives xi
    torch.manual_seed(5)
    independent = residual.act(obs)
    residual.held_noise = 0.36
    torch.manual_seed(5)
    residual.hold_noise(11)
    step = residual.act(obs)

    inputs = step.extras["features"].double()
    net = residual.residual_net.double()
    latent = net[:-1](inputs)
    mean = residual.residual_bound * torch.tanh(net[-1](latent).reshape(BATCH, 2, 4) / residual.residual_bound)
    std = residual.residual_log_std.double().exp()
    residual.float()
    xi = (independent.extras["residual"].double() - mean) / std
    w = torch.randn(BATCH, latent.shape[-1], 8, generator=torch.Generator().manual_seed(11)).double()
    held = torch.einsum("bl,blo->bo", latent / latent.norm(dim=-1, keepdim=True), w).reshape(BATCH, 2, 4)
    expected = mean + std * (0.8 * xi + 0.6 * held)
    torch.testing.assert_close(step.extras["residual"].double(), expected, rtol=0, atol=1e-5)
    normal = torch.distributions.Normal(mean, std)
    torch.testing.assert_close(step.logprobs.double(), normal.log_prob(expected).sum(-1), rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(residual.evaluate({}, step.actions, step.extras).logprobs, step.logprobs,
                               rtol=0, atol=1e-5)

    residual.held_noise = 1.0
    draws = []
    for global_seed, held_seed in ((1, 7), (2, 7), (3, 8), (4, None)):
        torch.manual_seed(global_seed)
        if held_seed is not None:
            residual.hold_noise(held_seed)
        draws.append(residual.act(obs).extras["residual"])
    assert torch.equal(draws[0], draws[1])  # held: the decision's own seed does not change it
    assert not torch.allclose(draws[0], draws[2]) and not torch.allclose(draws[0], draws[3])
    taken = torch.stack([residual.act(obs).extras["residual"] for _ in range(40)])  # w fresh each call
    with torch.no_grad():
        standardised = (taken - residual.residual_distribution(step.extras["features"])[0]) / std.float()
    assert abs(float(standardised.mean())) < 0.05 and abs(float(standardised.std()) - 1.0) < 0.05


def test_only_the_residual_policy_and_the_critic_train(checkpoint):
    residual = policy(checkpoint)
    trainable = {name.split(".")[0] for name, p in residual.named_parameters() if p.requires_grad}
    assert trainable == {"residual_net", "residual_log_std", "value_net"}
    assert residual.critic_modules == ("value_net",)
    assert "frozen" in residual.lora_refusal and "residual" in residual.demo_refusal


def test_bad_residual_options_are_refused(checkpoint):
    with pytest.raises(ValueError, match="residual_std and residual_bound must be > 0"):
        policy(checkpoint, residual_std=0.0)
    for options in ({"held_noise": 1.5}, {"held_noise": -0.1}, {"held_noise": 0.5, "held_noise_every": 0}):
        with pytest.raises(ValueError, match="held_noise must be in"):
            policy(checkpoint, **options)


def test_ppo_moves_the_noise_free_action_to_a_rewarded_one_the_vla_does_not_produce(checkpoint):
    """A one-step bandit: reward minus the squared distance of the first executed action to the
    VLA's noise-free action shifted by 0.5 in every dim."""
    residual = policy(checkpoint, residual_hidden=(32,))
    model = NormalizedPolicy(residual, {}, 10.0)
    obs = observations(seed=2)
    frame = {key: value[:1].expand(BATCH, *value.shape[1:]).clone() for key, value in obs.items()}
    target = residual.base(frame)[0][:, 0] + 0.5

    def reward(actions):
        return -((actions[:, 0] - target) ** 2).sum(-1)

    before, after = ppo_on_a_bandit(model, frame, reward)
    assert before == pytest.approx(-1.0, abs=1e-5)  # four dims 0.5 away
    assert after > before / 10, (before, after)


def test_readout_of_a_training_field_is_fitted_after_updates_and_acting_needs_the_features_only(checkpoint):
    """``residual_readout``: the residual policy and the critic also read a ridge readout of an
    observation field from the features. Unfitted it reads 0 (the start is the VLA's noise-free
    action); the trainer's :meth:`fit_readout` scores it on the batch (nan before any fit), folds the
    batch in and refits; the MLPs then read ``[features, readout(features)]`` (float64 reference),
    the trainer recomputes the log-probs from the batch without the field, the fit is buffers
    (saved and synced), and acting never needs the field."""
    from infinirl.models.ridge_readout import RidgeReadout

    residual, plain = policy(checkpoint, residual_readout="state", residual_readout_dim=5), policy(checkpoint)
    obs = observations()
    torch.testing.assert_close(residual.act(obs, deterministic=True).actions,
                               plain.act(obs, deterministic=True).actions, rtol=0, atol=START_ATOL)
    first = residual.act(obs)
    targets = first.extras["features"][:, :5] * 3.0 + torch.randn(BATCH, 5) * 0.01  # a field the features hold
    model = NormalizedPolicy(residual, {}, 10.0)
    metrics = model.fit_readout({"state": targets}, first.extras)
    assert metrics == {}  # nothing to score before the first fit
    assert residual.readout.fitted and float(residual.readout.count) == BATCH
    assert model.fit_readout({"state": targets}, first.extras)["train/readout_r2"] > 0.9  # now fitted: a score
    reference = RidgeReadout(first.extras["features"].shape[1], 5, penalty=residual.readout.penalty)
    for _ in range(2):
        reference.accumulate(first.extras["features"], targets)
    reference.refit()
    torch.testing.assert_close(residual.readout.weight, reference.weight)
    assert {"readout.weight", "readout.bias", "readout.sum_xx", "readout.count"} <= set(residual.state_dict())

    with torch.no_grad():
        residual.residual_net[-1].weight.normal_(0.0, 0.1)
    step = residual.act(obs)  # no 'state': acting reads the features only
    features = step.extras["features"].double()
    readout = (features @ residual.readout.weight[0] + residual.readout.bias[0]).clamp(-10, 10)
    raw = residual.residual_net.double()(torch.cat([features, readout], dim=-1)).reshape(BATCH, 2, 4)
    residual.float()
    mean = residual.residual_bound * torch.tanh(raw / residual.residual_bound)
    normal = torch.distributions.Normal(mean, residual.residual_log_std.double().exp())
    torch.testing.assert_close(step.logprobs.double(), normal.log_prob(step.extras["residual"].double()).sum(-1),
                               rtol=1e-5, atol=1e-4)
    evaluated = residual.evaluate({"state": targets}, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, rtol=0, atol=1e-5)
    assert not torch.allclose(readout.float(), torch.zeros_like(readout.float()))

    with pytest.raises(ValueError, match=r"residual_readout='state': the training batch's observation lacks"):
        model.fit_readout({}, first.extras)
    with pytest.raises(ValueError, match=r"residual_readout fits on extras\['features'\]"):
        model.fit_readout({"state": targets}, {"residual": first.extras["residual"]})
    with pytest.raises(ValueError, match=r"residual_readout='state' needs residual_readout_dim"):
        policy(checkpoint, residual_readout="state")
    with pytest.raises(ValueError, match=r"readout_groups must be >= 1 and readout_penalty > 0, got 0 and 0.01"):
        policy(checkpoint, residual_readout="state", residual_readout_dim=5, readout_groups=0)
    assert NormalizedPolicy(plain, {}, 10.0).fit_readout({"state": targets}, first.extras) == {}


def test_readout_groups_fit_one_readout_per_instruction(checkpoint):
    """``readout_groups``: rows are keyed by a hash of their instruction (recorded in extras, so
    the trainer's update and fit need no text), each instruction gets a readout fitted on its rows
    alone, and the trainer's log-probs still match the rollout's."""
    from infinirl.models.ridge_readout import RidgeReadout
    from infinirl.models.vla.residual import instruction_key

    residual = policy(checkpoint, residual_readout="state", residual_readout_dim=3, readout_groups=2)
    texts = ["press the button"] * (BATCH // 2) + ["open the door"] * (BATCH // 2)
    obs = {**observations(), "instruction": texts}
    first = residual.act(obs)
    keys = first.extras["readout_key"]
    assert keys.tolist() == [instruction_key(t) for t in texts] and instruction_key("open the door") == keys[-1]
    targets = first.extras["features"][:, :3] * torch.tensor([1.0, -2.0, 0.5]) + 1.0
    residual.fit_readout({"state": targets}, first.extras)
    half = slice(0, BATCH // 2)
    alone = RidgeReadout(first.extras["features"].shape[1], 3, penalty=residual.readout.penalty)
    alone.accumulate(first.extras["features"][half], targets[half])
    alone.refit()
    torch.testing.assert_close(residual.readout(first.extras["features"][half], keys[half]),
                               alone(first.extras["features"][half]), rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        residual.residual_net[-1].weight.normal_(0.0, 0.1)
    step = residual.act(obs)
    torch.testing.assert_close(residual.evaluate({}, step.actions, step.extras).logprobs, step.logprobs,
                               rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match=r"readout_groups > 1 reads extras\['readout_key'\]"):
        residual.evaluate({}, step.actions, {k: v for k, v in step.extras.items() if k != "readout_key"})
