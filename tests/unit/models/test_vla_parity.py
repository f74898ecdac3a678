"""π0 / π0.5 loaded from LeRobot-written checkpoints reproduce LeRobot's own outputs.

Each fixture folder was saved by LeRobot 0.4.4's ``PI0Policy`` / ``PI05Policy`` (random weights,
tiny sizes, the published key layout) with its processors, and ``reference.safetensors`` holds
what LeRobot computed from fixed raw inputs, noise and flow times. Our model, built from the
folder alone, must give the same preprocessed inputs, prefix states, velocity, sampled action
chunk and flow-matching loss to float32 tolerance.
"""

import pytest
import torch

from infinirl.models.vla.processor import resize_with_pad
from tests.unit.models.vla_fixtures import FAMILIES, load, raw_observation, reference

# Relative to the reference's largest magnitude: float32 reassociation across torch builds only.
RTOL = 1e-5


def assert_close(ours, theirs, what):
    scale = max(theirs.float().abs().max().item(), 1.0)
    error = (ours.float() - theirs.float()).abs().max().item()
    assert error <= RTOL * scale, f"{what}: max error {error:.3g} at scale {scale:.3g}"


@pytest.fixture(scope="module", params=FAMILIES)
def case(request):
    family = request.param
    vla = load(family)
    return family, vla, vla.inputs(raw_observation(family)), reference(family)


def test_preprocessing_matches(case):
    _, vla, inputs, ref = case
    for i, (image, mask) in enumerate(zip(inputs.images, inputs.image_masks, strict=True)):
        assert_close(image, ref[f"image.{i}"], f"camera {i}")
        assert torch.equal(mask, ref[f"image_mask.{i}"])
    assert torch.equal(inputs.tokens, ref["tokens"])
    assert torch.equal(inputs.token_mask, ref["token_mask"])
    if "normalized_state" in ref:
        assert_close(inputs.state[:, :ref["normalized_state"].shape[1]], ref["normalized_state"], "state")
    assert_close(vla.processor.actions_in(ref["raw.action"]), ref["normalized_actions"], "actions in")


def test_prefix_and_velocity_match(case):
    _, vla, x, ref = case
    with torch.no_grad():
        embeddings, pad_mask = vla.model.embed_prefix(x.images, x.image_masks, x.tokens, x.token_mask)
        prefix = vla.model.encode_prefix(x.images, x.image_masks, x.tokens, x.token_mask)
        velocity = vla.model.velocity(prefix, x.state, ref["x_t"], ref["time"])
    assert_close(embeddings, ref["prefix_embs"], "prefix embeddings")
    assert torch.equal(pad_mask, ref["prefix_pad_mask"])
    assert_close(prefix.hidden, ref["prefix_out"], "prefix hidden states")
    assert_close(velocity, ref["velocity"], "velocity")


def test_sampled_chunk_matches(case):
    _, vla, x, ref = case
    sampled = vla.model.sample_actions(x.images, x.image_masks, x.tokens, x.token_mask, x.state,
                                       noise=ref["noise"])
    assert_close(sampled, ref["sampled_normalized"], "sampled (normalised)")
    assert_close(vla.processor.actions_out(sampled), ref["sampled_actions"], "sampled actions")
    observation = raw_observation(case[0])
    assert_close(vla.predict_action_chunk(observation, noise=ref["noise"]), ref["sampled_actions"], "predict")


def test_flow_matching_loss_matches(case):
    family, vla, x, ref = case
    elements = vla.model.loss_elements(x.images, x.image_masks, x.tokens, x.token_mask, x.state,
                                       ref["normalized_actions"], noise=ref["noise"], time=ref["time"])
    assert_close(elements, ref["loss_elements"], "loss elements")
    action_dim = ref["raw.action"].shape[-1]
    loss = vla.loss(raw_observation(family), ref["raw.action"], noise=ref["noise"], time=ref["time"])
    assert_close(loss, ref["loss_elements"][..., :action_dim].mean(), "loss")


def test_loss_gradients_reach_both_stacks(case):
    family, vla, _, ref = case
    vla.zero_grad()
    vla.loss(raw_observation(family), ref["raw.action"], noise=ref["noise"], time=ref["time"]).backward()
    for name in ("vision_tower", "vlm", "expert", "action_in_proj"):
        grads = [p.grad for p in getattr(vla.model, name).parameters() if p.grad is not None]
        assert grads and any(g.abs().sum() > 0 for g in grads), f"no gradient reached {name}"
    vla.zero_grad()


def test_resize_with_pad_keeps_aspect_and_pads_black():
    """openpi's resize_with_pad: a 2:1 image fills the width and gets equal black bars."""
    image = torch.ones(1, 3, 8, 16)
    out = resize_with_pad(image, 8, 8)
    assert out.shape == (1, 3, 8, 8)
    assert torch.equal(out[:, :, 2:6], torch.ones(1, 3, 4, 8))
    assert torch.equal(out[:, :, :2], torch.zeros(1, 3, 2, 8)) and torch.equal(out[:, :, 6:], torch.zeros(1, 3, 2, 8))


@pytest.mark.parametrize("family", FAMILIES)
def test_bfloat16_runs_near_the_float32_reference(family):
    """bfloat16 weights (statistics and the denoising state stay float32): same actions to bf16 precision."""
    vla = load(family, dtype=torch.bfloat16)
    ref = reference(family)
    actions = vla.predict_action_chunk(raw_observation(family), noise=ref["noise"])
    assert actions.dtype == torch.float32
    scale = ref["sampled_actions"].abs().max().item()
    assert (actions - ref["sampled_actions"]).abs().max().item() <= 0.05 * scale
