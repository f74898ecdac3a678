"""VLAs on a real GPU: π0 / π0.5 and OpenVLA-OFT loaded on CUDA reproduce the references their own
code wrote (float32, TF32 off), bfloat16 on CUDA stays near them, and the RL policies (π0 family
and the small ``pi0_smollm2``) act, evaluate the same log-probs and back-propagate on CUDA.
Skipped without CUDA (conftest.py): ``pytest -m gpu tests/gpu``."""

import pytest
import torch

from infinirl.models.policies.base import build_policy
from infinirl.models.vla import save_vla
from tests.unit.models import vla_fixtures as pi0
from tests.unit.models import vla_oft_fixtures as oft
from tests.unit.models.test_vla_policy import env_obs as pi0_env_obs
from tests.unit.models.test_vla_policy import policy as pi0_policy
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla
from tests.unit.models.test_vla_smollm2 import env_obs as smollm2_env_obs

pytestmark = pytest.mark.gpu

# float32 on CUDA differs from the CPU reference by kernel reassociation only.
RTOL_F32 = 1e-4


@pytest.fixture(autouse=True)
def no_tf32():
    matmul, cudnn = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = matmul, cudnn


def assert_close(ours, theirs, rel, what):
    ours, theirs = ours.detach().float().cpu(), theirs.detach().float().cpu()
    scale = max(theirs.abs().max().item(), 1.0)
    error = (ours - theirs).abs().max().item()
    assert error <= rel * scale, f"{what}: max error {error:.3g} at scale {scale:.3g}"


@pytest.mark.parametrize("family", pi0.FAMILIES)
def test_pi0_family_on_cuda_reproduces_lerobot(family):
    vla = pi0.load(family, device="cuda")
    ref = pi0.reference(family)
    observation = pi0.raw_observation(family)
    assert vla.model.action_in_proj.weight.is_cuda
    # observation, noise, flow times and demonstrations in host memory, as a data loader gives them
    actions = vla.predict_action_chunk(observation, noise=ref["noise"])
    assert_close(actions, ref["sampled_actions"], RTOL_F32, "sampled actions")
    loss = vla.loss(observation, ref["raw.action"], noise=ref["noise"], time=ref["time"])
    action_dim = ref["raw.action"].shape[-1]
    assert_close(loss, ref["loss_elements"][..., :action_dim].mean(), RTOL_F32, "loss")
    loss.backward()
    assert all(p.grad is None or p.grad.is_cuda for p in vla.parameters())


@pytest.mark.parametrize("family", pi0.FAMILIES)
def test_pi0_family_in_bfloat16_on_cuda_stays_near_the_reference(family):
    vla = pi0.load(family, device="cuda", dtype=torch.bfloat16)
    ref = pi0.reference(family)
    actions = vla.predict_action_chunk(pi0.raw_observation(family), noise=ref["noise"].cuda())
    assert actions.dtype == torch.float32
    assert_close(actions, ref["sampled_actions"], 0.05, "bf16 sampled actions")


@pytest.mark.parametrize("head", ["l1", "discrete"])
def test_openvla_oft_on_cuda_reproduces_ofts_actions(head):
    bundle = oft.load(head=head, device="cuda")
    ref = oft.reference()
    actions = bundle.predict_action_chunk(oft.cameras(), oft.inputs()["tasks"], ref["raw.proprio"])
    for i in range(2):
        assert_close(actions[i], ref[f"{i}.{head}.actions"], RTOL_F32, f"{head} actions {i}")


def test_openvla_oft_in_bfloat16_on_cuda_runs_near_float32():
    ref = oft.reference()
    full = oft.load(head="l1", device="cuda").predict_action_chunk(oft.cameras(), oft.inputs()["tasks"],
                                                                   ref["raw.proprio"])
    half = oft.load(head="l1", device="cuda", dtype=torch.bfloat16).predict_action_chunk(
        oft.cameras(), oft.inputs()["tasks"], ref["raw.proprio"])
    assert torch.isfinite(half).all()
    assert_close(half, full, 0.1, "bf16 l1 actions")


def act_evaluate_backward(policy, obs):
    torch.manual_seed(1)
    step = policy.act(obs)
    assert step.logprobs.is_cuda and step.actions.is_cuda
    evaluated = policy.evaluate(obs, step.actions, step.extras)
    torch.testing.assert_close(evaluated.logprobs, step.logprobs, atol=1e-4, rtol=1e-5)
    policy.zero_grad()
    (evaluated.logprobs.sum() + evaluated.values.sum()).backward()
    grads = [p.grad for p in policy.parameters() if p.grad is not None]
    assert grads and all(g.is_cuda for g in grads) and any(g.abs().sum() > 0 for g in grads)


@pytest.mark.parametrize("family", pi0.FAMILIES)
def test_pi0_policy_acts_evaluates_and_trains_on_cuda(family):
    torch.manual_seed(0)
    act_evaluate_backward(pi0_policy(family).cuda(), pi0_env_obs(family))


def test_pi0_smollm2_policy_acts_evaluates_and_trains_on_cuda(tmp_path):
    folder = save_vla(tiny_vla(), tmp_path / "ckpt")
    torch.manual_seed(0)
    policy = build_policy("pi0_smollm2", checkpoint=str(folder), action_dim=4, chunk=2, cameras={"rgb": CAMERA},
                          state_key="proprio", value_hidden=8).cuda()
    act_evaluate_backward(policy, smollm2_env_obs())


def test_sft_runner_trains_on_cuda_and_resumes_on_the_cpu(tmp_path):
    """The SFT runner with ``device=cuda``: the model and its optimizer state on the GPU, batches
    moved over from host memory, an evaluation in MetaWorld acting from CUDA; the checkpoint it
    writes resumes with ``device=cpu`` (the change is recorded, not refused)."""
    pytest.importorskip("metaworld")
    pytest.importorskip("pyarrow")
    from infinirl.runners.sft import run
    from tests.integration.test_sft_pipeline import make_cfg, rows_of

    init = save_vla(tiny_vla(), tmp_path / "init")
    data = tmp_path / "demos"
    extra = {"model": {"init": str(init), "chunk_size": 3, "n_action_steps": 2, "num_inference_steps": 2}}
    done = run(make_cfg(tmp_path / "gpu", data, device="cuda", iterations=2, **extra))
    rows = rows_of(tmp_path / "gpu" / "metrics.jsonl")
    assert [r["step"] for r in rows] == [1, 2] and all(r["train/loss"] > 0 for r in rows)
    assert rows[-1]["train/peak_memory_bytes"] > 0 and "eval/success_rate" in rows[-1]
    assert done["samples"] == 8
    resumed = run(make_cfg(tmp_path / "gpu", data, device="cpu", iterations=3, **extra))
    assert resumed["samples"] == 12
