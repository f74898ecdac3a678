"""The ``openvla_oft`` policy: act and evaluate agree, log-probs are the categorical / Gaussian
densities written out in float64, gradients reach the VLA, the env gets unnormalised actions."""

import math

import pytest
import torch

from infinirl.models.policies.base import build_policy
from tests.unit.models.vla_oft_fixtures import ARCHITECTURE, FOLDER, cameras, inputs, reference


def build(head, **kwargs):
    options = dict(checkpoint=str(FOLDER), action_dim=7, chunk=3, head=head, unnorm_key=inputs()["unnorm_key"],
                   num_images=2, architecture=str(ARCHITECTURE))
    options.update(kwargs)
    return build_policy("openvla_oft", **options)


def observation() -> dict:
    rgb, wrist = cameras()
    return {"rgb": rgb, "wrist_rgb": wrist, "state": reference()["raw.proprio"].float(),
            "instruction": inputs()["tasks"]}


@pytest.fixture(scope="module")
def discrete():
    return build("discrete")


@pytest.fixture(scope="module")
def l1():
    return build("l1", init_log_std=-0.5)


def test_discrete_act_evaluate_agree_and_match_a_float64_categorical(discrete):
    torch.manual_seed(0)
    obs = observation()
    step = discrete.act(obs)
    assert step.actions.shape == (2, 3, 7) and step.logprobs.shape == (2, 3) and step.values.shape == (2,)
    tokens = step.extras["tokens"]
    assert tokens.shape == (2, 8, 7) and tokens.min() >= 0 and tokens.max() < 256
    new = discrete.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(new.logprobs, step.logprobs, rtol=1e-5, atol=1e-5)
    # float64 from the reference's action-token logits
    ref = torch.stack([reference()[f"{i}.discrete.action_logits"] for i in range(2)]).double()
    logp = torch.log_softmax(ref, -1).reshape(2, 8, 7, 256)
    expected = logp.gather(-1, tokens[..., None]).squeeze(-1)[:, :3].sum(-1)
    torch.testing.assert_close(new.logprobs.double(), expected, rtol=1e-4, atol=1e-4)
    entropy = -(logp.exp() * logp).sum(-1)[:, :3].sum(-1)
    torch.testing.assert_close(new.entropy.double(), entropy, rtol=1e-4, atol=1e-4)
    # the env actions are the sampled tokens' bins, unnormalised
    bins = discrete.vla.model.token_actions(discrete.vla.model.slice_to_token(tokens.flatten(1)))
    torch.testing.assert_close(step.actions.double(), discrete.vla.processor.env_actions(bins)[:, :3].float().double())


def test_discrete_deterministic_is_the_arg_max(discrete):
    step = discrete.act(observation(), deterministic=True)
    ref = torch.stack([reference()[f"{i}.discrete.action_logits"] for i in range(2)])
    assert torch.equal(step.extras["tokens"].flatten(1), ref.argmax(-1))


def test_discrete_gradients_reach_llm_vision_and_critic(discrete):
    obs = observation()
    step = discrete.act(obs)
    out = discrete.evaluate(obs, step.actions, step.extras)
    (out.logprobs.sum() + out.values.sum()).backward()
    model = discrete.vla.model
    for module in (model.vision, model.llm.model, model.llm.lm_head, discrete.value_net):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.parameters())
    discrete.zero_grad(set_to_none=True)


def test_l1_gaussian_act_evaluate_agree_and_match_the_formula(l1):
    torch.manual_seed(0)
    obs = observation()
    step = l1.act(obs)
    normalized = step.extras["normalized"]
    new = l1.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(new.logprobs, step.logprobs, rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        mean = l1.vla.model.regress(torch.stack([reference()[f"{i}.l1.hidden"] for i in range(2)])).double()
    std = math.exp(-0.5)
    density = (-((normalized.double() - mean) ** 2) / (2 * std ** 2) - math.log(std) - 0.5 * math.log(2 * math.pi))
    torch.testing.assert_close(new.logprobs.double(), density[:, :3].sum(-1), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(step.actions.double(), l1.vla.processor.env_actions(normalized)[:, :3].float().double())
    (new.logprobs.sum()).backward()
    assert l1.log_std.grad is not None and l1.vla.model.action_head.fc2.weight.grad.abs().sum() > 0
    l1.zero_grad(set_to_none=True)


def test_l1_deterministic_is_the_reference_chunk(l1):
    step = l1.act(observation(), deterministic=True)
    expected = torch.stack([reference()[f"{i}.l1.actions"] for i in range(2)])[:, :3]
    torch.testing.assert_close(step.actions[..., :6].double(), expected[..., :6], rtol=1e-5, atol=1e-5)
    # the gripper as OFT's LIBERO eval sends it: normalize_gripper_action, then invert_gripper_action
    torch.testing.assert_close(step.actions[..., 6].double(), -torch.sign(2 * expected[..., 6] - 1))


def test_policy_checks():
    with pytest.raises(ValueError, match="chunks of 3 x 6"):
        build("discrete", action_dim=6)
    with pytest.raises(ValueError, match="evaluate needs extras"):
        build("l1").evaluate(observation(), torch.zeros(2, 3, 7), {})


def test_libero_gripper_goes_to_the_env_as_oft_eval_sends_it(discrete):
    """OFT learns LIBERO's gripper as 0 = close, 1 = open (unnormalised); LIBERO takes -1 = open, +1 = close."""
    processor = discrete.vla.processor
    normalized = torch.zeros(5, 8, 7)
    normalized[:, :, -1] = torch.tensor([0.0, 0.2, 0.5, 0.8, 1.0])[:, None]
    out = processor.env_actions(normalized)
    assert out[:, 0, -1].tolist() == [1.0, 1.0, 0.0, -1.0, -1.0]  # close, close, (sign 0 as OFT), open, open
    torch.testing.assert_close(out[..., :-1], processor.actions_out(normalized)[..., :-1])
    # the policy's env actions take that path, its log-probs still score the sampled tokens
    torch.manual_seed(0)
    step = discrete.act(observation())
    assert set(step.actions[..., -1].unique().tolist()) <= {-1.0, 0.0, 1.0}
    # a platform without OpenVLA's flip (ALOHA) passes the gripper through unnormalised
    from dataclasses import replace

    from infinirl.models.vla.openvla_oft.config import PLATFORMS
    assert PLATFORMS["libero"].invert_gripper and not PLATFORMS["aloha"].invert_gripper
    processor.config = replace(processor.config, platform=replace(processor.config.platform, invert_gripper=False))
    try:
        torch.testing.assert_close(processor.env_actions(normalized), processor.actions_out(normalized))
    finally:
        processor.config = replace(processor.config, platform=PLATFORMS["libero"])
