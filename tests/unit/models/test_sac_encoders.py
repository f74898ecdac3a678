"""SAC's observation encoders: shapes, who trains the encoder, the random shift against a padded-crop
reference, and one pixel SAC update against a step-by-step reference."""

import copy

import numpy as np
import pytest
import torch

from infinirl.algorithms.sac import sac_actor_loss
from infinirl.components.sac_learner import SACAgent, SACNetSpec, SACUpdateSpec
from infinirl.envs.base import ActionSpace
from infinirl.models.sac_encoders import (
    ENCODERS,
    EncodedActor,
    EncodedCritic,
    PixelEncoder,
    random_shift,
    random_shift_observations,
)
from infinirl.models.sac_nets import EnsembleQ, SquashedGaussianActor
from infinirl.registry import UnknownNameError

SPACE = ActionSpace.box([-1.0, -1.0], [1.0, 1.0])
CAMERAS = {"front": (20, 20), "wrist": (16, 24)}
CNN = {"channels": (4, 4), "strides": (2, 1), "feature_dim": 8}


def pixel_obs(n=6, state_dim=3, seed=0, cameras=CAMERAS):
    g = torch.Generator().manual_seed(seed)
    obs = {"state": torch.randn(n, state_dim, generator=g)}
    for name, (h, w) in cameras.items():
        obs[f"pixels.{name}"] = torch.randint(0, 256, (n, h, w, 3), generator=g, dtype=torch.uint8)
    return obs


def pixel_batch(n=6, seed=0):
    g = torch.Generator().manual_seed(seed + 100)
    return {"obs": pixel_obs(n, seed=seed), "next_obs": pixel_obs(n, seed=seed + 1),
            "action": torch.rand(n, 2, generator=g) * 2 - 1, "reward": torch.randn(n, generator=g),
            "terminated": (torch.rand(n, generator=g) < 0.3).float()}


def pixel_net(**extra):
    return SACNetSpec(actor_hidden=(16,), critic_hidden=(16,), encoder="cnn", encoder_options=dict(CNN), **extra)


def test_encoder_registry_and_shapes():
    assert {"state", "cnn"} <= set(ENCODERS.names())
    assert SACNetSpec().build_encoder(5) is None  # state: today's networks, no encoder in front
    assert isinstance(SACNetSpec().build_actor(5, SPACE), SquashedGaussianActor)
    with pytest.raises(ValueError, match="at least one camera"):
        pixel_net().build_encoder(3, {})
    with pytest.raises(UnknownNameError, match="registered: .*cnn"):
        SACNetSpec(encoder="resnet").build_encoder(3, CAMERAS)
    with pytest.raises(ValueError, match="too small"):
        PixelEncoder({"tiny": (4, 4)}, 3, channels=(4, 4), strides=(2, 2))

    encoder = PixelEncoder(CAMERAS, 3, **CNN)
    obs = pixel_obs()
    assert encoder(obs).shape == (6, 8 + 3) and encoder.out_dim == 11
    torch.testing.assert_close(encoder(obs)[:, 8:], obs["state"])  # the state is concatenated after the encoder
    actor = pixel_net().build_actor(3, SPACE, CAMERAS)
    assert isinstance(actor, EncodedActor)
    action, logprob, u = actor.sample(obs, torch.Generator().manual_seed(0))
    assert action.shape == (6, 2) and logprob.shape == (6,) and u.shape == (6, 2)
    critic = pixel_net().build_critic(3, SPACE, actor.encoder)
    assert isinstance(critic, EncodedCritic) and critic.encoder is actor.encoder
    assert critic(obs, action).shape == (2, 6)
    # The actor's weights (what a robot receives) carry the encoder.
    assert any(name.startswith("encoder.trunks.front") for name in actor.state_dict())


def test_frames_are_normalised_inside_the_network():
    encoder = PixelEncoder({"cam": (8, 8)}, 0, channels=(2,), strides=(1,), feature_dim=4)
    frames = torch.full((1, 8, 8, 3), 255, dtype=torch.uint8)
    trunk_input = []
    encoder.trunks["cam"].register_forward_pre_hook(lambda module, args: trunk_input.append(args[0]))
    encoder({"pixels.cam": frames})
    assert trunk_input[0].shape == (1, 3, 8, 8) and torch.all(trunk_input[0] == 0.5)


def test_the_actor_loss_does_not_reach_the_encoder():
    agent = SACAgent(pixel_net(), SACUpdateSpec(seed=1), 3, SPACE, cameras=CAMERAS)
    encoder_ids = {id(p) for p in agent.actor.encoder.parameters()}
    actor_ids = {id(p) for group in agent.actor_optim.param_groups for p in group["params"]}
    critic_ids = {id(p) for group in agent.critic_optim.param_groups for p in group["params"]}
    assert not encoder_ids & actor_ids and encoder_ids <= critic_ids  # the critic's optimiser trains the encoder
    action, logprob, _ = agent.actor.sample(pixel_obs(), agent.generator)
    (logprob.sum() + action.sum()).backward()
    assert all(p.grad is None for p in agent.actor.encoder.parameters())
    assert all(p.grad is not None for p in agent.actor.head.parameters())


def test_random_shift_matches_the_padded_crop_and_is_deterministic_under_a_seed():
    frames = torch.randint(0, 256, (5, 7, 9, 3), generator=torch.Generator().manual_seed(0), dtype=torch.uint8)
    pad = 2
    shifted = random_shift(frames, pad, torch.Generator().manual_seed(3))
    shifts = torch.randint(0, 2 * pad + 1, (5, 2), generator=torch.Generator().manual_seed(3)).numpy()
    for b, (dy, dx) in enumerate(shifts):
        padded = np.pad(frames[b].numpy(), ((pad, pad), (pad, pad), (0, 0)), mode="edge")
        np.testing.assert_array_equal(shifted[b].numpy(), padded[dy:dy + 7, dx:dx + 9])
    again = random_shift(frames, pad, torch.Generator().manual_seed(3))
    assert torch.equal(shifted, again) and shifted.dtype == torch.uint8
    assert not torch.equal(shifted, random_shift(frames, pad, torch.Generator().manual_seed(4)))
    assert random_shift(frames, 0) is frames
    obs = pixel_obs()
    moved = random_shift_observations(obs, 2, torch.Generator().manual_seed(0))
    assert moved["state"] is obs["state"] and moved["pixels.front"].shape == obs["pixels.front"].shape


def _reference_adam_step(params, grads, lr, eps=1e-8, betas=(0.9, 0.999)):
    """Adam's first step, written out: m = (1-b1) g, v = (1-b2) g^2, bias-corrected."""
    for p, g in zip(params, grads):
        m, v = (1 - betas[0]) * g, (1 - betas[1]) * g * g
        m_hat, v_hat = m / (1 - betas[0]), v / (1 - betas[1])
        p.data -= lr * m_hat / (v_hat.sqrt() + eps)


def test_one_pixel_update_matches_the_step_by_step_reference():
    spec = SACUpdateSpec(gamma=0.9, tau=0.1, init_alpha=0.5, autotune_alpha=False, seed=3)
    agent = SACAgent(pixel_net(augment_pad=2), spec, 3, SPACE, cameras=CAMERAS)
    batch = pixel_batch()
    actor, critic, target = (copy.deepcopy(m) for m in (agent.actor, agent.critic, agent.critic_target))
    actor.encoder = critic.encoder  # the deep copies share one encoder, as the agent's modules do
    noise, shifts = torch.Generator(), torch.Generator()
    noise.set_state(agent.generator.get_state())
    shifts.set_state(agent.augment_generator.get_state())
    obs = random_shift_observations(batch["obs"], 2, shifts)
    next_obs = random_shift_observations(batch["next_obs"], 2, shifts)

    with torch.no_grad():
        next_action, next_logprob, _ = actor.sample(next_obs, noise)
        y = batch["reward"] + 0.9 * (1 - batch["terminated"]) * (target(next_obs, next_action).min(0).values
                                                                 - 0.5 * next_logprob)
    q = critic(obs, batch["action"])
    critic_loss = sum(0.5 * ((q[k] - y) ** 2).mean() for k in range(2))
    critic_params = list(critic.parameters())
    _reference_adam_step(critic_params, torch.autograd.grad(critic_loss, critic_params), spec.critic_lr)
    encoder_after_critic = copy.deepcopy(critic.encoder.state_dict())

    critic.requires_grad_(False)
    action, logprob, _ = actor.sample(obs, noise)
    actor_loss = sac_actor_loss(logprobs=logprob, q_values=critic(obs, action), alpha=torch.tensor(0.5)).loss
    head_params = list(actor.head.parameters())
    _reference_adam_step(head_params, torch.autograd.grad(actor_loss, head_params), spec.actor_lr)

    metrics = agent.update(batch)
    torch.testing.assert_close(metrics["train/critic_loss"], critic_loss.detach())
    torch.testing.assert_close(metrics["train/actor_loss"], actor_loss.detach())
    for name, value in agent.critic.state_dict().items():
        torch.testing.assert_close(value, critic.state_dict()[name], rtol=1e-5, atol=1e-6, msg=name)
    for name, value in agent.actor.head.state_dict().items():
        torch.testing.assert_close(value, actor.head.state_dict()[name], rtol=1e-5, atol=1e-6, msg=name)
    for name, value in agent.actor.encoder.state_dict().items():  # moved by the critic step only
        torch.testing.assert_close(value, encoder_after_critic[name], rtol=1e-5, atol=1e-6, msg=name)
    for name, value in agent.critic_target.state_dict().items():  # the targets average the encoder too
        expected = 0.9 * target.state_dict()[name] + 0.1 * agent.critic.state_dict()[name]
        torch.testing.assert_close(value, expected, msg=name)


def test_pixel_agent_state_round_trip_continues_identically_with_a_flow_actor():
    net = pixel_net(augment_pad=1, actor="flow", flow={"num_steps": 2, "hidden": (16,)})
    a = SACAgent(net, SACUpdateSpec(seed=5, batch_size=6), 3, SPACE, cameras=CAMERAS)
    assert isinstance(a.actor.head, torch.nn.Module) and isinstance(a.critic.head, EnsembleQ)
    a.update(pixel_batch(seed=0))
    b = SACAgent(net, SACUpdateSpec(seed=6, batch_size=6), 3, SPACE, cameras=CAMERAS)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    for i in range(1, 3):
        ma, mb = a.update(pixel_batch(seed=i)), b.update(pixel_batch(seed=i))
        assert {k: float(v) for k, v in ma.items()} == {k: float(v) for k, v in mb.items()}
    for (name, x), (_, y) in zip(a.named_tensors(), b.named_tensors()):
        assert torch.equal(x, y), name
