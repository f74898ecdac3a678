"""SAC from pixels on a real GPU: the CUDA agent (conv encoder, random shifts) updates like the CPU
agent (the same noise and shift draws from its CPU generators, float rounding apart).
Skipped without CUDA (conftest.py): ``pytest -m gpu tests/gpu``."""

import pytest
import torch

from infinirl.components.sac_learner import SACAgent, SACUpdateSpec
from tests.unit.models.test_sac_encoders import CAMERAS, SPACE, pixel_batch, pixel_net

pytestmark = pytest.mark.gpu


def weights(agent):
    return torch.cat([t.detach().float().cpu().reshape(-1) for _, t in agent.named_tensors()])


def on(batch, device):
    return {key: ({k: v.to(device) for k, v in value.items()} if isinstance(value, dict) else value.to(device))
            for key, value in batch.items()}


def test_the_cuda_pixel_agent_updates_like_the_cpu_agent():
    net = pixel_net(augment_pad=2)
    cpu = SACAgent(net, SACUpdateSpec(seed=3), 3, SPACE, cameras=CAMERAS)
    gpu = SACAgent(net, SACUpdateSpec(seed=3), 3, SPACE, device="cuda", cameras=CAMERAS)
    assert all(p.is_cuda for p in gpu.critic.encoder.parameters())
    assert torch.equal(weights(cpu), weights(gpu))
    for i in range(10):
        cpu.update(pixel_batch(seed=i))
        gpu.update(on(pixel_batch(seed=i), "cuda"))
    torch.testing.assert_close(weights(gpu), weights(cpu), rtol=0, atol=1e-3)

