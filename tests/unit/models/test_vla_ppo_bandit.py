"""The PPO update moves a VLA the right way: a one-step bandit (reward: minus the squared distance of
the first executed action to a target) with the tiny random ``pi0_smollm2`` policy and the embodied
runner's own ``ppo_update`` on flow-SDE log-probs. Both the sampled and the noise-free (ODE) policy
must approach the target, with every denoising step stochastic, with one, with LoRA adapters, and
with Flow Policy Optimization's flow-matching-loss ratios instead of densities."""

import pytest
import torch

from infinirl.algorithms.embodied_ppo import PPOSpec, ppo_update
from infinirl.components.embodied_policy import NormalizedPolicy
from infinirl.engines.policy_lora import PolicyLoraSpec, apply_policy_lora
from infinirl.models.policies.base import build_policy
from infinirl.models.vla import save_vla
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla

BATCH, TARGET = 64, torch.tensor([0.5, -0.5, 0.5, -0.5])


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    return str(save_vla(tiny_vla(), tmp_path_factory.mktemp("vla") / "policy"))


def distance_reward(actions: torch.Tensor) -> torch.Tensor:
    return -((actions[:, 0] - TARGET) ** 2).sum(-1)


@pytest.mark.parametrize("sde_steps, lora, likelihood", [("all", None, "flow_sde"), ("one", None, "flow_sde"),
                                                         ("all", PolicyLoraSpec(r=8, alpha=16.0), "flow_sde"),
                                                         ("all", None, "fpo")])
def test_ppo_moves_the_vla_toward_the_rewarded_action(checkpoint, sde_steps, lora, likelihood):
    torch.manual_seed(0)
    policy = build_policy("pi0_smollm2", checkpoint=checkpoint, action_dim=4, chunk=2, cameras={"rgb": CAMERA},
                          state_key="proprio", value_hidden=8, instruction="reach", sde_steps=sde_steps,
                          likelihood=likelihood)
    if lora is not None:
        apply_policy_lora(policy, lora)
    model = NormalizedPolicy(policy, {}, 10.0)
    frame = torch.randint(0, 256, (1, 16, 16, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(1))
    obs = {"rgb": frame.expand(BATCH, -1, -1, -1).clone(), "proprio": torch.zeros(BATCH, 4)}
    lr = 1e-3 if lora is None else 3e-3
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr)
    ppo = PPOSpec(lr=lr, anneal_lr=False, epochs=2, mini_batches=2, critic=False, max_grad_norm=1.0)
    generator = torch.Generator().manual_seed(2)

    def noise_free_reward() -> float:
        with torch.no_grad():
            return float(distance_reward(model.act(obs, deterministic=True).actions).mean())

    before, sampled = noise_free_reward(), []
    for iteration in range(12):
        with torch.no_grad():
            step = model.act(obs)
        reward = distance_reward(step.actions)
        sampled.append(float(reward.mean()))
        batch = {"obs": obs, "actions": step.actions, "logprobs": step.logprobs, "values": torch.zeros(BATCH),
                 "advantages": reward - reward.mean(), "returns": reward, "extras": step.extras,
                 "step_mask": torch.ones(step.actions.shape[:2], dtype=torch.bool)}
        ppo_update(model, optimizer, batch, iteration, ppo, generator=generator)
    after = noise_free_reward()
    assert after > before / 2, (before, after)  # rewards are negative: half the squared distance or less
    assert sum(sampled[-3:]) / 3 > sum(sampled[:3]) / 3 + 1.0, sampled
