"""OpenVLA-OFT loaded from a folder written by OFT's own code equals OFT's outputs (float32 tolerance).

The reference ran each observation alone (batch size 1, its only mode); ours runs both together
(prompts of different lengths), so these also prove that batching changes nothing."""

import pytest
import torch

from tests.unit.models.vla_oft_fixtures import cameras, inputs, load, reference


@pytest.fixture(scope="module")
def l1():
    return load(head="l1")


@pytest.fixture(scope="module")
def discrete():
    return load(head="discrete")


def close(ours, theirs, rel=1e-5):
    theirs = theirs.to(ours.dtype)
    scale = theirs.abs().max().clamp_min(1.0)
    assert (ours - theirs).abs().max() <= rel * scale, (ours - theirs).abs().max()


def test_preprocessing_matches_the_reference_processor(l1):
    ref = reference()
    x = l1.inputs(cameras(), inputs()["tasks"], ref["raw.proprio"])
    for i in range(2):
        ids = x["input_ids"][i, :x["lengths"][i]]
        # the tokenizer's prompt, then Llama-2's "▁" (29871) that predict_action appends
        assert ids[:-1].tolist() == ref[f"{i}.input_ids"].tolist() and ids[-1] == 29871
        close(x["pixel_values"][i], ref[f"{i}.pixel_values"])
        close(x["proprio"][i], ref[f"{i}.proprio_normalized"], rel=1e-12)


def test_l1_head_hidden_states_and_actions(l1):
    ref = reference()
    x = l1.inputs(cameras(), inputs()["tasks"], ref["raw.proprio"])
    with torch.no_grad():
        states = l1.action_states(x)
    actions = l1.predict_action_chunk(cameras(), inputs()["tasks"], ref["raw.proprio"])
    assert actions.shape == (2, 8, 7)
    for i in range(2):
        close(states.hidden[i], ref[f"{i}.l1.hidden"])
        close(actions[i], ref[f"{i}.l1.actions"])


def test_discrete_head_action_token_logits_and_actions(discrete):
    ref = reference()
    x = discrete.inputs(cameras(), inputs()["tasks"], ref["raw.proprio"])
    with torch.no_grad():
        logits = discrete.model.action_logits(discrete.action_states(x).hidden)
    actions = discrete.predict_action_chunk(cameras(), inputs()["tasks"], ref["raw.proprio"])
    for i in range(2):
        assert logits[i].shape == (56, 256)
        close(logits[i], ref[f"{i}.discrete.action_logits"])
        assert torch.equal(logits[i].argmax(-1), ref[f"{i}.discrete.action_logits"].argmax(-1))
        close(actions[i], ref[f"{i}.discrete.actions"], rel=1e-12)


def test_token_to_bin_mapping_is_openvlas(discrete):
    """id t -> bin clip(32000 - t - 1, 0, 254): the last id is bin 0 (-1 + 1/255), the first two share bin 254."""
    model = discrete.model
    ids = torch.tensor([[31999, 31745, 31744, 31999, 31999, 31999, 31999]])
    centers = model.token_actions(ids)[0, 0]
    edges = torch.linspace(-1, 1, 256, dtype=torch.float64)
    assert centers[0] == (edges[0] + edges[1]) / 2 and centers[1] == centers[2] == (edges[254] + edges[255]) / 2
    assert model.slice_to_token(torch.tensor([0, 255])).tolist() == [31744, 31999]


def test_resize_true_accepts_other_sizes():
    small = [image.permute(0, 3, 1, 2).float() / 255 for image in cameras()]
    big = [torch.nn.functional.interpolate(image, size=(64, 64), mode="nearest") for image in small]
    resizing = load(head="l1", resize=True)
    pixels = resizing.processor.pixel_values(big)
    assert pixels.shape == (2, 12, 32, 32) and torch.isfinite(pixels).all()


def test_gradients_reach_vision_llm_and_heads(l1):
    ref = reference()
    model = l1.model
    x = l1.inputs(cameras(), inputs()["tasks"], ref["raw.proprio"])
    loss = model.regress(l1.action_states(x).hidden).abs().mean()
    loss.backward()
    for module in (model.vision.featurizers[0], model.vision.featurizers[1], model.projector, model.llm.model,
                   model.action_head, model.proprio_projector):
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        assert grads and any(g.abs().sum() > 0 for g in grads), type(module).__name__
    model.zero_grad(set_to_none=True)
