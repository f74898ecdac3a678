"""SAC's learner on a real GPU: the CUDA agent updates like the CPU agent (the same noise draws,
float rounding apart), a checkpoint moves between the devices and continues, and the runner
computes on the GPU it is placed on and resumes exactly there. Skipped without CUDA
(conftest.py): ``pytest -m gpu tests/gpu``."""

import io

import pytest
import torch

pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from infinirl.components.sac_learner import SACAgent, SACNetSpec, SACUpdateSpec  # noqa: E402
from tests.integration.test_sac_pipeline import make_cfg  # noqa: E402
from tests.unit.test_sac_agent import SPACE, make_batch  # noqa: E402

pytestmark = pytest.mark.gpu

NET = SACNetSpec(actor_hidden=(32, 32), critic_hidden=(32, 32))


def weights(agent):
    return torch.cat([t.detach().float().cpu().reshape(-1) for _, t in agent.named_tensors()])


def on(batch, device):
    return {key: value.to(device) for key, value in batch.items()}


@pytest.mark.parametrize("actor", ["gaussian", "flow"])
def test_the_cuda_agent_updates_like_the_cpu_agent(actor):
    net = NET if actor == "gaussian" else SACNetSpec(actor_hidden=(32, 32), critic_hidden=(32, 32), actor="flow",
                                                     flow={"num_steps": 3, "hidden": (32, 32)})
    cpu = SACAgent(net, SACUpdateSpec(seed=3), 5, SPACE)
    gpu = SACAgent(net, SACUpdateSpec(seed=3), 5, SPACE, device="cuda")
    assert all(p.is_cuda for p in gpu.actor.parameters()) and gpu.log_alpha.is_cuda
    assert torch.equal(weights(cpu), weights(gpu))  # the same initial weights on either device
    for i in range(20):
        cpu_metrics, gpu_metrics = cpu.update(make_batch(seed=i)), gpu.update(on(make_batch(seed=i), "cuda"))
    assert not torch.equal(weights(cpu), weights(SACAgent(net, SACUpdateSpec(seed=3), 5, SPACE)))  # trained
    if actor == "gaussian":  # the same noise from SAC's CPU generator: the same updates, up to rounding
        torch.testing.assert_close(weights(gpu), weights(cpu), rtol=0, atol=1e-4)
        for key in ("train/critic_loss", "train/actor_loss", "train/alpha"):
            torch.testing.assert_close(gpu_metrics[key].cpu(), cpu_metrics[key], rtol=1e-3, atol=1e-4)
    else:  # the flow draws from the device's own generator: a different, finite, reproducible stream
        assert torch.isfinite(weights(gpu)).all()


def test_a_gpu_checkpoint_continues_on_the_cpu_and_back():
    gpu = SACAgent(NET, SACUpdateSpec(seed=4), 5, SPACE, device="cuda")
    for i in range(3):
        gpu.update(on(make_batch(seed=i), "cuda"))
    buffer = io.BytesIO()
    torch.save(gpu.state_dict(), buffer)
    buffer.seek(0)
    cpu = SACAgent(NET, SACUpdateSpec(seed=9), 5, SPACE)
    cpu.load_state_dict(torch.load(buffer, map_location="cpu", weights_only=False))
    assert torch.equal(weights(cpu), weights(gpu))
    for i in range(3, 8):
        gpu.update(on(make_batch(seed=i), "cuda"))
        cpu.update(make_batch(seed=i))
    torch.testing.assert_close(weights(cpu), weights(gpu), rtol=0, atol=1e-4)
    back = SACAgent(NET, SACUpdateSpec(seed=9), 5, SPACE, device="cuda")
    back.load_state_dict(cpu.state_dict())
    assert all(t.is_cuda for _, t in back.named_tensors()) and torch.equal(weights(back), weights(cpu))


def test_the_runner_learns_on_the_gpu_and_resumes_exactly(ray_cluster, tmp_path):
    from infinirl.runners.sac import run

    on_gpu = {"placement": {"collector": "0", "learner": "0"}}
    straight = run(make_cfg(tmp_path / "straight", 4, **on_gpu))
    run(make_cfg(tmp_path / "resumed", 2, **on_gpu))
    resumed = run(make_cfg(tmp_path / "resumed", 4, **on_gpu))
    assert straight["devices"] == {"learner": "cuda:0"}
    for key in ("weights_sha256", "actor_weights_sha256", "buffer_sha256", "env_steps"):
        assert resumed[key] == straight[key], key
    cpu = run(make_cfg(tmp_path / "cpu", 4, learner={"device": "cpu"}, **on_gpu))
    assert cpu["devices"] == {"learner": "cpu"}  # learner.device=cpu keeps it off the GPU it is placed on
