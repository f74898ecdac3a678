"""LoRA on a robot policy: adapters on the chosen linear layers, the rest frozen but the value head,
the adapted policy acting as the plain one until it trains, and the merged weights giving a plain
policy that computes what the adapted one does (what the rollout receives)."""

import pytest
import torch

from infinirl.engines.policy_lora import PolicyLoraSpec, apply_policy_lora, lora_targets, merged_policy_weights
from infinirl.models.policies.base import build_policy
from infinirl.models.vla import save_vla
from tests.unit.models.test_vla_smollm2 import CAMERA, env_obs, tiny_vla


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return str(save_vla(tiny_vla(), tmp_path_factory.mktemp("lora") / "ckpt"))


def plain_policy(checkpoint):
    torch.manual_seed(0)  # the value head's initial weights
    return build_policy("pi0_smollm2", checkpoint=checkpoint, action_dim=4, chunk=2, cameras={"rgb": CAMERA},
                        state_key="proprio", value_hidden=8)


def test_a_fresh_noise_head_trains_in_full_not_through_adapters(checkpoint):
    """Flow-Noise's std head is new (zero weights): adapters on it would be a rank-r copy of a
    layer that should learn freely, so LoRA trains it in full though ``train_fully`` omits it."""
    torch.manual_seed(0)
    policy = build_policy("pi0_smollm2", checkpoint=checkpoint, action_dim=4, chunk=2, cameras={"rgb": CAMERA},
                          state_key="proprio", value_hidden=8, likelihood="flow_noise")
    spec = PolicyLoraSpec(r=2, alpha=4.0)
    assert not any("std_net" in t for t in lora_targets(policy, spec))
    apply_policy_lora(policy, spec)
    trainable = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert {"std_net.weight", "std_net.bias", "value_net.0.weight"} <= trainable
    assert not any(n.startswith("std_net.") and ".lora_" in n for n, _ in policy.named_parameters())


def logprobs_of(policy, step):
    return policy.evaluate(env_obs(), step.actions, step.extras).logprobs


def test_adapters_train_the_value_head_trains_the_rest_is_frozen(checkpoint):
    policy = plain_policy(checkpoint)
    spec = PolicyLoraSpec(r=2, alpha=4.0, target_modules=["q_proj", "v_proj"])
    targets = lora_targets(policy, spec)
    assert targets and all(t.endswith(("q_proj", "v_proj")) for t in targets)
    apply_policy_lora(policy, spec)
    trainable = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert trainable == {n for n, _ in policy.named_parameters() if ".lora_" in n or n.startswith("value_net.")}
    assert trainable and not any(n.startswith("vla.") and ".lora_" not in n for n in trainable)
    assert len([n for n in trainable if ".lora_A." in n]) == len(targets)


def test_the_adapted_policy_acts_as_the_plain_one_then_its_merged_weights_reproduce_it(checkpoint):
    plain, adapted = plain_policy(checkpoint), plain_policy(checkpoint)
    plan = apply_policy_lora(adapted, PolicyLoraSpec(r=4, alpha=8.0))
    torch.manual_seed(1)
    step = plain.act(env_obs())
    torch.testing.assert_close(logprobs_of(adapted, step), logprobs_of(plain, step), atol=1e-6, rtol=1e-6)

    optimizer = torch.optim.Adam([p for p in adapted.parameters() if p.requires_grad], lr=1e-2)
    frozen = {n: p.detach().clone() for n, p in adapted.named_parameters() if not p.requires_grad}
    for _ in range(3):
        optimizer.zero_grad()
        evaluated = adapted.evaluate(env_obs(), step.actions, step.extras)
        (-evaluated.logprobs.sum() + evaluated.values.square().sum()).backward()
        optimizer.step()
    assert all(torch.equal(p, frozen[n]) for n, p in adapted.named_parameters() if n in frozen)
    trained = logprobs_of(adapted, step)
    assert not torch.allclose(trained, logprobs_of(plain, step), atol=1e-4)

    merged = dict(merged_policy_weights(adapted.state_dict().items(), plan))
    assert set(merged) == set(plain.state_dict())  # the plain policy's names, no adapter entries
    plain.load_state_dict(merged)
    torch.testing.assert_close(logprobs_of(plain, step), trained, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(plain.evaluate(env_obs(), step.actions, step.extras).values,
                               adapted.evaluate(env_obs(), step.actions, step.extras).values)


def test_names_that_match_nothing_are_one_line_naming_the_key(checkpoint):
    policy = plain_policy(checkpoint)
    with pytest.raises(ValueError, match=r"^actor.lora.target_modules=\['qkv'\] matches no linear layer.*q_proj"):
        apply_policy_lora(policy, PolicyLoraSpec(target_modules=["qkv"]))
    with pytest.raises(ValueError, match=r"^actor.lora.train_fully names \['critic'\]"):
        apply_policy_lora(plain_policy(checkpoint), PolicyLoraSpec(train_fully=["critic"]))
    with pytest.raises(ValueError, match=r"^actor.lora.target_modules='q_proj': give 'all-linear' or a list"):
        PolicyLoraSpec(target_modules="q_proj").check()


def test_adapters_under_fsdp2_train_and_merge_as_unsharded(checkpoint):
    """actor.strategy=fsdp with actor.lora (FSDP2, one gloo rank): frozen base weights and trainable
    adapters share the sharded parameter groups; the update, the frozen weights and the merged
    plain weights the rollout receives match the unsharded adapted policy's. The policy is called
    through the actor's wrapper's ``forward``, the call FSDP2's hooks see."""
    from infinirl.components.embodied_policy import NormalizedPolicy
    from infinirl.engines.distributed import init_distributed
    from infinirl.engines.parallel import DATA_PARALLEL

    init_distributed()
    spec = PolicyLoraSpec(r=4, alpha=8.0)
    unsharded, sharded = NormalizedPolicy(plain_policy(checkpoint), {}), NormalizedPolicy(plain_policy(checkpoint), {})
    torch.manual_seed(2)  # the adapters' A matrices: random, identical on both (as on every rank)
    plan = apply_policy_lora(unsharded, spec)
    torch.manual_seed(2)
    assert apply_policy_lora(sharded, spec) == plan
    parallel = DATA_PARALLEL.get("fsdp")()
    sharded = parallel.wrap(sharded)
    torch.manual_seed(1)
    step = unsharded.act(env_obs())

    def train(model, optimizer):
        for _ in range(3):
            optimizer.zero_grad()
            logprobs, _, values = model(env_obs(), step.actions, step.extras, False)
            (-logprobs.sum() + values.square().sum()).backward()
            optimizer.step()
        with torch.no_grad():
            return model(env_obs(), step.actions, step.extras, False)[0]

    expected_logprobs = train(unsharded, torch.optim.Adam([p for p in unsharded.parameters() if p.requires_grad],
                                                          lr=1e-2))
    logprobs = train(sharded, parallel.build_optimizer(sharded, lr=1e-2, eps=1e-8))
    torch.testing.assert_close(logprobs, expected_logprobs, atol=1e-5, rtol=1e-5)

    merged = dict(merged_policy_weights(parallel.full_weights(sharded), plan))
    expected = dict(merged_policy_weights(unsharded.state_dict().items(), plan))
    assert set(merged) == set(expected)
    assert not any(".lora_" in name for name in merged)
    for name, tensor in expected.items():
        torch.testing.assert_close(merged[name], tensor, atol=1e-5, rtol=1e-5, msg=name)
