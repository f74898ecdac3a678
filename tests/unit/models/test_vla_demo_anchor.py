"""PPO's behaviour-cloning anchor on a VLA policy: the VLA's own flow-matching loss on dataset frames,
drawn as a function of (seed, iteration, step) alone, split over ranks without changing the gradient."""

import pytest
import torch

pytest.importorskip("pyarrow")

from infinirl.components.demo_anchor import DemoAnchor, DemoAnchorSpec, read_frames  # noqa: E402
from infinirl.components.embodied_policy import NormalizedPolicy  # noqa: E402
from infinirl.models.vla.policy import PiZeroSmolLM2Policy  # noqa: E402
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla  # noqa: E402
from tests.unit.runners.test_sft import synthetic_dataset  # noqa: E402


@pytest.fixture(scope="module")
def spec(tmp_path_factory):
    root = tmp_path_factory.mktemp("demos") / "ds"
    synthetic_dataset(root)
    return DemoAnchorSpec(data=str(root), coef=2.0, decay=0.5, batch_size=6, augment_shift=2, seed=3)


def policy():
    return NormalizedPolicy(PiZeroSmolLM2Policy(tiny_vla(), action_dim=4, chunk=2, cameras={"rgb": CAMERA},
                                                state_key="proprio", value_hidden=8), {})


def gradient(model, loss) -> torch.Tensor:
    model.zero_grad(set_to_none=True)
    loss.backward()
    return torch.cat([p.grad.reshape(-1) for p in model.parameters() if p.grad is not None])


def test_the_anchor_is_the_vlas_flow_matching_loss_on_seeded_frames(spec):
    model = policy()
    anchor = DemoAnchor(spec, model.policy.demo_chunk)
    assert anchor.chunk == model.policy.vla.config.chunk_size  # the whole chunk SFT cloned, not the executed 2
    state = torch.get_rng_state()
    loss, metrics = anchor.loss(model, 1, 4)
    assert torch.equal(torch.get_rng_state(), state)  # its draws move no one else's generator
    assert metrics["train/bc_weight"] == 2.0 * 0.5 and torch.equal(loss, 1.0 * metrics["train/bc_loss"])
    again, _ = anchor.loss(model, 1, 4)
    assert torch.equal(again, loss)  # a resumed run draws the step again identically
    assert not torch.equal(anchor.loss(model, 1, 5)[0], loss) and not torch.equal(anchor.loss(model, 2, 4)[0], loss)

    # the same as the VLA's own loss on those frames with those draws
    observation, actions, valid, draws = anchor.batch(1, 4, model.policy)
    assert draws["noise"].shape == (6, anchor.chunk, model.policy.vla.config.max_action_dim)
    expected = model.policy.vla.loss(observation, actions, noise=draws["noise"], time=draws["time"],
                                     action_mask=valid)
    torch.testing.assert_close(metrics["train/bc_loss"], expected.detach(), rtol=0, atol=0)


def test_two_ranks_clone_with_the_gradient_of_one(spec):
    model = policy()
    frames = read_frames(spec)
    whole = gradient(model, DemoAnchor(spec, model.policy.demo_chunk, frames=frames).loss(model, 0, 1)[0])
    parts = [gradient(model, DemoAnchor(spec, model.policy.demo_chunk, rank, 2, frames).loss(model, 0, 1)[0])
             for rank in (0, 1)]
    torch.testing.assert_close(parts[0] + parts[1], whole, rtol=1e-4, atol=1e-6)
