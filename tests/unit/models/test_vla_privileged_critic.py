"""An asymmetric critic for the frozen-VLA policies (``critic_obs``, :class:`~infinirl.models.vla.frozen.FrozenVLA`):
the value reads an observation field the policy never sees (MetaWorld's full ``state``) beside the
policy's features. The value is exactly the head on both; the policy's actions and log-probs do
not depend on the field; the same value comes from act, evaluate (the batch) and value; the
embodied runner fills the field's size from the env's spec and names a field the env lacks."""

import numpy as np
import pytest
import torch

from infinirl.components.embodied_policy import policy_kwargs
from infinirl.envs.base import ArraySpec
from tests.unit.models.test_vla_steered import BATCH, observations, tiny_checkpoint
from tests.unit.models.test_vla_steered import policy as build

FORMS = ["pi0_smollm2_residual", "pi0_smollm2_steered"]
STATE_DIM = 7


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory)


def with_state(obs, seed=4):
    generator = torch.Generator().manual_seed(seed)
    return {**obs, "state": torch.randn(len(obs["proprio"]), STATE_DIM, generator=generator)}


@pytest.mark.parametrize("name", FORMS)
def test_the_value_is_the_head_on_the_features_and_the_field_and_the_policy_ignores_the_field(checkpoint, name):
    model = build(checkpoint, name=name, critic_obs="state", critic_obs_dim=STATE_DIM)
    obs = with_state(observations())
    torch.manual_seed(3)
    step = model.act(obs)
    inputs = step.extras["features"]
    expected = model.value_net.double()(torch.cat([inputs.double(), obs["state"].double()], -1)).squeeze(-1)
    model.float()
    torch.testing.assert_close(step.values.double(), expected, rtol=1e-5, atol=1e-5)
    evaluated = model.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluated.values, step.values, rtol=0, atol=1e-6)
    torch.testing.assert_close(model.value(obs), step.values, rtol=0, atol=1e-5)

    other = with_state(observations(), seed=9)  # the same frames and proprio, another privileged state
    torch.manual_seed(3)
    moved = model.act(other)
    assert torch.equal(moved.actions, step.actions) and torch.equal(moved.logprobs, step.logprobs)
    assert not torch.allclose(moved.values, step.values)
    grads = torch.autograd.grad(model.evaluate(obs, step.actions, step.extras).values.sum(), model.value_net[0].weight)
    assert grads[0][:, -STATE_DIM:].abs().sum() > 0  # the field's columns of the first layer train


@pytest.mark.parametrize("name", FORMS)
def test_a_missing_or_misshapen_field_and_a_missing_size_are_named(checkpoint, name):
    model = build(checkpoint, name=name, critic_obs="state", critic_obs_dim=STATE_DIM)
    with pytest.raises(ValueError, match=r"critic_obs='state': the observation lacks that field"):
        model.act(observations())
    short = {**observations(), "state": torch.zeros(BATCH, 3)}
    with pytest.raises(ValueError, match=r"has 3 values, the critic was built for critic_obs_dim=7"):
        model.act(short)
    with pytest.raises(ValueError, match=r"critic_obs='state' needs critic_obs_dim"):
        build(checkpoint, name=name, critic_obs="state")


def test_without_it_the_critic_reads_the_features_alone(checkpoint):
    model = build(checkpoint, name="pi0_smollm2_residual")
    step = model.act(observations())
    torch.testing.assert_close(step.values, model.value_net(step.extras["features"]).squeeze(-1), rtol=0, atol=1e-6)


def test_the_runner_fills_the_fields_size_from_the_env_spec_and_names_an_unknown_field():
    class Space:
        is_discrete, shape = False, (4,)
        low, high = -np.ones(4), np.ones(4)

    spec = {"state": ArraySpec((39,), "float32"), "proprio": ArraySpec((4,), "float32"),
            "rgb": ArraySpec((16, 16, 3), "uint8")}
    kwargs = policy_kwargs("pi0_smollm2_residual", {"critic_obs": "state"}, spec, Space(), 2)
    assert kwargs["critic_obs_dim"] == 39
    with pytest.raises(ValueError, match=r"critic_obs='goal' is not an observation field of this env; it has "
                                         r"\['proprio', 'rgb', 'state'\]"):
        policy_kwargs("pi0_smollm2_residual", {"critic_obs": "goal"}, spec, Space(), 2)


def test_the_runner_fills_the_readout_fields_size_and_names_an_unknown_field():
    class Space:
        is_discrete, shape = False, (4,)
        low, high = -np.ones(4), np.ones(4)

    spec = {"state": ArraySpec((39,), "float32"), "proprio": ArraySpec((4,), "float32")}
    kwargs = policy_kwargs("pi0_smollm2_residual", {"residual_readout": "state"}, spec, Space(), 2)
    assert kwargs["residual_readout_dim"] == 39 and "critic_obs_dim" not in kwargs
    with pytest.raises(ValueError, match=r"policy.kwargs.residual_readout='goal' is not an observation field"):
        policy_kwargs("pi0_smollm2_residual", {"residual_readout": "goal"}, spec, Space(), 2)
