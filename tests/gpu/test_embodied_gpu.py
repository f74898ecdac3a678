"""Embodied PPO on a real GPU: the update on CUDA trains like the CPU one; the runner computes on
the GPU it is placed on (actor and rollout), syncs weights to a CPU rollout as well, and a run
resumes exactly on the GPU. Skipped without CUDA (conftest.py): ``pytest -m gpu tests/gpu``."""

import dataclasses
import json

import pytest
import torch

pytest.importorskip("gymnasium")

from infinirl.components.embodied_actor import ppo_update  # noqa: E402
from tests.integration.test_embodied_pipeline import make_cfg, straight_and_resumed  # noqa: E402
from tests.unit.test_compiled_step import fixed_shape_updates_step_like_eager  # noqa: E402
from tests.unit.test_embodied_ppo_update import PPO, flat, policy_and_batch  # noqa: E402

pytestmark = pytest.mark.gpu

ON_GPU_0 = {"env": "0", "rollout": "0", "actor": "0"}


def on(value, device):
    if isinstance(value, dict):
        return {key: on(v, device) for key, v in value.items()}
    return value.to(device)


@pytest.mark.parametrize("compile_", [False, True], ids=["eager", "compiled"])
def test_ppo_update_on_gpu_matches_the_cpu_update(compile_):
    build, batch = policy_and_batch()
    cpu = build()
    cpu_metrics = ppo_update(cpu, torch.optim.Adam(cpu.parameters(), lr=PPO.lr), batch, 0, PPO)

    gpu = build().cuda()
    optimizer = torch.optim.Adam(gpu.parameters(), lr=PPO.lr, fused=True)
    gpu_metrics = ppo_update(gpu, optimizer, on(batch, "cuda"), 0, dataclasses.replace(PPO, compile=compile_))
    assert all(p.is_cuda for p in gpu.parameters())
    assert not torch.equal(flat(cpu), flat(build()))  # the update moved the weights
    torch.testing.assert_close(flat(gpu).cpu(), flat(cpu), rtol=0, atol=1e-4)
    for key in ("train/policy_loss", "train/value_loss", "train/grad_norm"):
        assert gpu_metrics[key] == pytest.approx(cpu_metrics[key], rel=1e-3, abs=1e-5), key


def test_fixed_shape_compiled_steps_on_cuda_skip_guards_and_step_like_eager():
    """The compiled step's guard skipping (``fixed_shapes``, what ppo_update passes) on CUDA: the
    steps after each update's first match eager backward / clip / Adam, and a new mini-batch
    shape still compiles its own graph."""
    fixed_shape_updates_step_like_eager("cuda")


def metrics_rows(run_dir):
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_runner_trains_on_the_gpu_and_resumes_exactly(ray_cluster, tmp_path):
    straight, resumed = straight_and_resumed(tmp_path, 4, ON_GPU_0, 1)
    assert straight["devices"] == resumed["devices"] == {"rollout": "cuda:0", "actor": "cuda:0"}
    rows = metrics_rows(tmp_path / "straight")
    assert [r["step"] for r in rows] == [0, 1, 2, 3, 4]
    assert max(r["train/logprob_mismatch"] for r in rows[1:]) < 1e-4


def test_compiled_actor_and_rollout_train_and_resume_exactly_on_the_gpu(ray_cluster, tmp_path):
    """actor.compile + rollout.compile (the MetaWorld configs' settings) on CUDA: the compiled
    step and act run on the GPU, the trainer agrees with the rollout, a resumed run continues."""
    compiled = {"actor": {"anneal_lr": False, "compile": True}, "rollout": {"compile": True}}
    straight, resumed = straight_and_resumed(tmp_path, 2, ON_GPU_0, 1, **compiled)
    assert straight["devices"] == resumed["devices"] == {"rollout": "cuda:0", "actor": "cuda:0"}
    rows = metrics_rows(tmp_path / "straight")
    assert rows[1]["rollout/act_compiled"] == 1.0
    assert max(r["train/logprob_mismatch"] for r in rows[1:]) < 1e-4


def test_gpu_actor_syncs_weights_to_a_cpu_rollout(ray_cluster, tmp_path):
    summary = run_cfg(tmp_path, rollout={"device": "cpu"})
    assert summary["devices"] == {"rollout": "cpu", "actor": "cuda:0"}
    # the CPU rollout samples with the weights the GPU actor trained: their log-probs agree
    assert max(r["train/logprob_mismatch"] for r in metrics_rows(tmp_path)[1:]) < 1e-4


def run_cfg(tmp_path, **extra):
    from infinirl.runners.embodied import run

    return run(make_cfg(tmp_path, 2, ON_GPU_0, 1, **extra))
