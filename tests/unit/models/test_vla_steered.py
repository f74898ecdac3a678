"""The steered VLA (``pi0_smollm2_steered``, :mod:`infinirl.models.vla.steered`): RL over the
initial noise of the frozen VLA's deterministic sampler. At the start it samples exactly as the VLA
does; its log-probs are the noise's Gaussian density (float64 reference), recomputed by the
trainer from the batch alone; only the two small networks train; PPO moves its noise-free action
toward a rewarded one."""

import pytest
import torch

from infinirl.algorithms.embodied_ppo import PPOSpec, ppo_update
from infinirl.components.embodied_policy import NormalizedPolicy
from infinirl.models.policies.base import build_policy
from infinirl.models.vla import save_vla
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla

BATCH = 32


def tiny_checkpoint(tmp_path_factory) -> str:
    torch.manual_seed(0)
    return str(save_vla(tiny_vla(), tmp_path_factory.mktemp("vla") / "policy"))


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory)


def policy(checkpoint, name="pi0_smollm2_steered", **options):
    torch.manual_seed(0)
    return build_policy(name, checkpoint=checkpoint, action_dim=4, chunk=2, cameras={"rgb": CAMERA},
                        state_key="proprio", instruction="reach", **options)


def observations(batch=BATCH, seed=1):
    generator = torch.Generator().manual_seed(seed)
    return {"rgb": torch.randint(0, 256, (batch, 16, 16, 3), dtype=torch.uint8, generator=generator),
            "proprio": torch.randn(batch, 4, generator=generator)}


def test_at_the_start_it_samples_as_the_vla_does(checkpoint):
    """mu = 0 and sigma = 1: the steered policy's sampled chunk is the VLA's noise-free sampler from
    the same standard-normal draw."""
    steered, plain = policy(checkpoint), policy(checkpoint, name="pi0_smollm2")
    obs = observations()
    torch.manual_seed(5)
    sampled = steered.act(obs)
    torch.manual_seed(5)
    reference = plain.act(obs, deterministic=True)
    torch.testing.assert_close(sampled.actions, reference.actions, rtol=0, atol=1e-6)
    assert torch.equal(sampled.extras["noise"].reshape(reference.extras["chain"][:, 0].shape),
                       reference.extras["chain"][:, 0])
    noise_free = steered.act(obs, deterministic=True)
    assert torch.equal(noise_free.extras["noise"], torch.zeros_like(noise_free.extras["noise"]))


def test_logprobs_are_the_noises_density_and_the_trainer_recomputes_them_from_the_batch(checkpoint, monkeypatch):
    steered = policy(checkpoint, noise_std=0.7)
    with torch.no_grad():
        steered.noise_net[-1].bias.normal_(0.0, 0.5)  # a mean away from 0
        steered.noise_log_std.normal_(-0.3, 0.1)
    step = steered.act(observations())
    noise, features = step.extras["noise"].double(), step.extras["features"].double()
    mean = steered.noise_bound * torch.tanh(steered.noise_net.double()(features) / steered.noise_bound)
    std = steered.noise_log_std.double().exp()
    reference = torch.distributions.Normal(mean, std).log_prob(noise).sum(-1)
    torch.testing.assert_close(step.logprobs[:, 0].double(), reference, rtol=1e-5, atol=1e-4)
    assert torch.equal(step.logprobs[:, 1:], torch.zeros_like(step.logprobs[:, 1:]))
    steered.float()

    def no_vla(*args, **kwargs):
        raise AssertionError("evaluate ran the VLA")

    monkeypatch.setattr(steered.vla.model, "encode_prefix", no_vla)
    evaluated = steered.evaluate({}, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, rtol=0, atol=1e-5)
    entropy = torch.distributions.Normal(mean, std).entropy().sum(-1)
    torch.testing.assert_close(evaluated.entropy[:, 0].double(), entropy, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(evaluated.values, step.values, rtol=0, atol=1e-6)


def test_only_the_noise_policy_and_the_critic_train(checkpoint):
    steered = policy(checkpoint)
    trainable = {name.split(".")[0] for name, p in steered.named_parameters() if p.requires_grad}
    assert trainable == {"noise_net", "noise_log_std", "value_net"}
    assert steered.critic_modules == ("value_net",)


def test_bad_steering_options_are_refused(checkpoint):
    with pytest.raises(ValueError, match="noise_std and noise_bound must be > 0"):
        policy(checkpoint, noise_std=0.0)


def test_ppo_steers_the_noise_free_action_toward_the_rewarded_one(checkpoint):
    """A one-step bandit: reward minus the squared distance of the first executed action to the
    action the VLA gives from one particular noise (so the target is one it can reach)."""
    steered = policy(checkpoint, noise_hidden=(32,))
    model = NormalizedPolicy(steered, {}, 10.0)
    obs = observations(seed=2)
    frame = {key: value[:1].expand(BATCH, *value.shape[1:]).clone() for key, value in obs.items()}
    _, x, prefix = steered.features(frame)
    target_noise = torch.full((BATCH, *steered.noise_shape), 1.5)
    target = steered.decode(x, prefix, target_noise)[:, 0]

    def reward(actions):
        return -((actions[:, 0] - target) ** 2).sum(-1)

    before, after = ppo_on_a_bandit(model, frame, reward)
    assert after > before / 10, (before, after)  # rewards are negative: a tenth of the squared distance


def ppo_on_a_bandit(model, frame, reward, iterations=15):
    """PPO (no critic, advantages reward minus the batch mean) on one repeated frame: the mean
    reward of the noise-free action before and after."""
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=3e-2)
    ppo = PPOSpec(lr=3e-2, anneal_lr=False, epochs=4, mini_batches=2, critic=False, max_grad_norm=1.0)
    generator = torch.Generator().manual_seed(2)
    with torch.no_grad():
        before = float(reward(model.act(frame, deterministic=True).actions).mean())
    for iteration in range(iterations):
        with torch.no_grad():
            step = model.act(frame)
        r = reward(step.actions)
        batch = {"obs": frame, "actions": step.actions, "logprobs": step.logprobs, "values": torch.zeros(BATCH),
                 "advantages": r - r.mean(), "returns": r, "extras": step.extras,
                 "step_mask": torch.ones(step.actions.shape[:2], dtype=torch.bool)}
        ppo_update(model, optimizer, batch, iteration, ppo, generator=generator)
    with torch.no_grad():
        after = float(reward(model.act(frame, deterministic=True).actions).mean())
    return before, after
