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


@pytest.mark.parametrize("family", FAMILIES)
def test_float16_runs_near_the_float32_reference(family):
    """float16's range ends at -65504: the mask bias must stay finite there, or a fully masked row
    (a padding token, a missing camera) turns to NaN and leaks into every row through the cache."""
    from infinirl.models.vla.layers import masked_value

    assert torch.isinf(torch.tensor(-2.3819763e38, dtype=torch.float16))  # openpi's constant
    assert torch.isfinite(torch.tensor(masked_value(torch.float16), dtype=torch.float16) - 30000)  # plus a score
    vla = load(family, dtype=torch.float16)
    ref = reference(family)
    actions = vla.predict_action_chunk(raw_observation(family), noise=ref["noise"])
    assert torch.isfinite(actions).all()
    scale = ref["sampled_actions"].abs().max().item()
    assert (actions - ref["sampled_actions"]).abs().max().item() <= 0.05 * scale


def test_bfloat16_time_embedding_is_computed_from_float32_times():
    """The sine-cosine features of t are computed in float32 and then cast: bfloat16 keeps 8 bits of t
    (0.7373 becomes 0.7383), which would turn the fastest features (period 4e-3) by a quarter turn."""
    from infinirl.models.vla.model import time_embedding

    vla = load("pi05", dtype=torch.bfloat16)
    model, config = vla.model, vla.model.config
    time = torch.tensor([0.7373, 0.123456], dtype=torch.float32)
    x_t = torch.zeros(2, config.chunk_size, config.max_action_dim)
    with torch.no_grad():
        _, _, cond = model.embed_suffix(None, x_t, time)
        width = config.architecture.expert.width

        def condition(embedded):
            return torch.nn.functional.silu(model.time_mlp_out(torch.nn.functional.silu(model.time_mlp_in(embedded))))

        exact = time_embedding(time, width, config.min_period, config.max_period).to(torch.bfloat16)
        rounded = time_embedding(time.to(torch.bfloat16), width, config.min_period, config.max_period)
        assert torch.equal(cond, condition(exact))
        assert not torch.equal(exact, rounded)
