"""``rollout.compile``: the compiled ``act`` samples what the eager one samples.

The same seed must give the same actions (up to float rounding of the network), the same
log-probs and values, and leave the random generator in the same state, so a compiled rollout
and an eager one draw the same noise step after step; and a weight sync (in-place copies into
the policy, as :meth:`EmbodiedRolloutWorker.load_weights` does) must reach the compiled function
without a recompile that would read stale weights."""

import pytest
import torch

from infinirl.components.embodied_rollout import PolicySpec, compiled_act
from infinirl.envs.base import ActionSpace, ArraySpec
from infinirl.runners.embodied_config import find_cxx_compiler

pytestmark = pytest.mark.skipif(find_cxx_compiler() is None,
                                reason="torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")

SPEC = {"state": ArraySpec((39,), "float32")}
ACTIONS = ActionSpace.box([-1.0] * 4, [1.0] * 4)


def policy(seed: int):
    torch.manual_seed(seed)
    return PolicySpec(name="mlp_gaussian", options={}).build(SPEC, ACTIONS).eval()


def assert_same_step(eager, compiled):
    torch.testing.assert_close(compiled.actions, eager.actions, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(compiled.logprobs, eager.logprobs, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(compiled.values, eager.values, rtol=1e-5, atol=1e-6)


@pytest.fixture
def restore_fallback_random():
    """compiled_act sets an inductor option process-wide; put it back for the tests that follow.
    (Not monkeypatch: since pytest 9.2 its undo deletes attributes that are not in the target's
    ``__dict__``, and deleting an inductor option hides it from inductor itself.)"""
    import torch._inductor.config as inductor_config

    previous = inductor_config.fallback_random
    yield
    inductor_config.fallback_random = previous


@torch.no_grad()
def test_compiled_act_draws_the_eager_noise_and_follows_weight_syncs(restore_fallback_random):
    model = policy(0)
    assert model.keys == ["state"]  # the observation normaliser is part of what is compiled
    act = compiled_act(model)
    obs = {"state": torch.randn(4, 39)}
    for trial in range(3):  # the first call compiles; later ones reuse the graph
        torch.manual_seed(100 + trial)
        eager = model.act(obs)
        after_eager = torch.get_rng_state()
        torch.manual_seed(100 + trial)
        compiled = act(obs)
        assert torch.equal(torch.get_rng_state(), after_eager)  # the same draws, no more, no fewer
        assert_same_step(eager, compiled)
        assert not torch.equal(compiled.actions[:, 0], model.policy.actor(model.normalize(obs)["state"]))  # sampled

    # A weight sync copies new tensors into the same parameters and buffers: the compiled act
    # must use them (different weights, different actions), agreeing with eager again.
    new = policy(1)
    own = model.state_dict()
    for name, tensor in new.state_dict().items():
        own[name].copy_(tensor)
    for name in model.keys:
        model.obs_rms[name].mean.fill_(0.5)
        model.obs_rms[name].var.fill_(4.0)
    torch.manual_seed(7)
    eager = model.act(obs)
    torch.manual_seed(7)
    compiled = act(obs)
    assert_same_step(eager, compiled)
    torch.manual_seed(7)
    assert not torch.allclose(compiled.values, policy(0).act(obs).values)
