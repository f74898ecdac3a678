"""The small ``pi0_smollm2`` VLA: Llama streams in the joint loop, SmolLM2's first layers, the
prefix cache, checkpoint round trips, the RL policy and its bad inputs.

Tiny random sizes (and the fixtures' word-level tokenizer) everywhere except the one test that
loads the embedded SmolLM2 (skipped when it is not installed)."""

import json
import math

import pytest
import torch
from transformers import LlamaConfig
from transformers.models.llama.modeling_llama import LlamaDecoderLayer, LlamaModel, LlamaRotaryEmbedding

from infinirl.models import smollm2
from infinirl.models.policies.base import build_policy
from infinirl.models.vla import load_vla, save_vla
from infinirl.models.vla.config import ConvStemSpec, LlamaSpec, VLAArchitecture, VLAConfig
from infinirl.models.vla.layers import DecoderStack, Stream, attention_bias, block_mask, mixture_forward
from infinirl.models.vla.save import PREPROCESSOR_STATS
from infinirl.models.vla.smollm2_vla import SmolVLASpec, build_vla, load_smollm2_layers, pi0_smollm2_config
from tests.unit.models.vla_fixtures import FIXTURES, TOKENIZER

CAMERA = "observation.images.corner"
TINY_VLM = LlamaSpec(width=24, depth=2, mlp_dim=40, num_heads=3, num_kv_heads=1, head_dim=8, rope_theta=100.0)
TINY_EXPERT = LlamaSpec(width=18, depth=2, mlp_dim=24, num_heads=3, num_kv_heads=1, head_dim=8, rope_theta=100.0)
STATS = {"observation.state": {"mean": [0.1, -0.2, 0.3, 0.0], "std": [1.0, 2.0, 0.5, 1.0]},
         "action": {"mean": [0.0, 0.1, -0.1, 0.2], "std": [0.5, 0.5, 1.0, 2.0]}}


def tiny_config(**extra) -> VLAConfig:
    architecture = VLAArchitecture(vlm=TINY_VLM, expert=TINY_EXPERT, vision=ConvStemSpec(channels=(8, 16), groups=4),
                                   vocab_size=288)
    options = dict(family="pi0_smollm2", architecture=architecture, camera_keys=(CAMERA,), state_dim=4, action_dim=4,
                   chunk_size=3, n_action_steps=3, max_state_dim=4, max_action_dim=4, num_inference_steps=3,
                   image_resolution=(16, 16), tokenizer_max_length=8, instructions={"reach": "pick up the cube"})
    options.update(extra)
    return VLAConfig(**options)


def tiny_vla(seed=0, **extra):
    torch.manual_seed(seed)
    vla = build_vla(tiny_config(**extra), STATS, tokenizer=TOKENIZER)
    vla.eval()
    return vla


def observation(batch=2, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return {CAMERA: torch.randint(0, 256, (batch, 16, 16, 3), dtype=torch.uint8, generator=generator),
            "observation.state": torch.randn(batch, 4, generator=generator),
            "task": ["reach", "open the top drawer"][:batch]}


def one_line(error) -> str:
    message = str(error.value)
    assert "\n" not in message, message
    return message


# ---- the Llama stream -----------------------------------------------------------------------


def test_llama_stream_is_transformers_decoder_layer_float64():
    """One Llama layer through the joint loop (prefix alone) equals LlamaDecoderLayer, same weights."""
    torch.manual_seed(0)
    spec = LlamaSpec(width=24, depth=1, mlp_dim=40, num_heads=3, num_kv_heads=1, head_dim=8, rope_theta=1000.0)
    stack = DecoderStack(spec, vocab_size=10, embed=False).double()
    for parameter in stack.parameters():  # norms start at ones: make them matter
        parameter.data.normal_()
    reference = LlamaDecoderLayer(stack.config, 0).double()
    reference.load_state_dict(stack.layers[0].state_dict())
    hidden = torch.randn(2, 5, 24, dtype=torch.float64)
    pad = torch.tensor([[True] * 5, [True, True, True, True, False]])
    mask = block_mask(pad, torch.zeros(2, 5, dtype=torch.long))
    bias = attention_bias(mask, torch.float64)
    positions = torch.arange(5)[None].expand(2, -1)
    rotary = stack.rotary_embedding()
    assert isinstance(rotary, LlamaRotaryEmbedding)
    (ours,), _ = mixture_forward([Stream(stack, hidden)], bias, positions, rotary)
    cos, sin = rotary(hidden, positions)
    expected = stack.norm(reference(hidden, attention_mask=bias, position_ids=positions,
                                    position_embeddings=(cos, sin)))
    assert torch.allclose(ours, expected, atol=1e-12, rtol=0)


def test_llama_embeddings_are_not_scaled_and_gemma_ones_are():
    llama = DecoderStack(TINY_VLM, vocab_size=10, embed=True)
    tokens = torch.tensor([[1, 2, 3]])
    assert torch.equal(llama.embed(tokens), llama.embed_tokens(tokens))
    gemma = DecoderStack(VLAArchitecture.from_json(FIXTURES / "architecture.json").vlm, vocab_size=10, embed=True)
    assert torch.equal(gemma.embed(tokens), gemma.embed_tokens(tokens) * math.sqrt(gemma.spec.width))


@pytest.mark.skipif(smollm2.find_gguf() is None and not (smollm2.converted_dir() / smollm2.PROVENANCE_FILE).is_file(),
                    reason=f"SmolLM2 not installed: {smollm2.INSTALL_HINT}")
def test_first_k_layers_of_smollm2_reproduce_llama_model():
    """Our VLM stack loaded from SmolLM2's first 2 layers gives LlamaModel's hidden states after 2
    layers (its final norm applied) on a prompt, under the causal mask LlamaModel uses."""
    folder = smollm2.ensure_converted()
    config = pi0_smollm2_config(SmolVLASpec(language_layers=2), camera_keys=(CAMERA,), state_dim=4, action_dim=4)
    stack = DecoderStack(config.architecture.vlm, config.architecture.vocab_size, embed=True)

    class Holder(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.vlm = stack

    load_smollm2_layers(Holder(), folder)
    reference_config = LlamaConfig.from_pretrained(str(folder))
    reference_config.num_hidden_layers = 2
    reference = LlamaModel.from_pretrained(str(folder), config=reference_config, dtype=torch.float32).eval()
    from transformers import AutoTokenizer

    tokens = AutoTokenizer.from_pretrained(str(folder))(["pick and place a puck to a goal"],
                                                       return_tensors="pt")["input_ids"]
    with torch.no_grad():
        expected = reference(input_ids=tokens).last_hidden_state
        pad = torch.ones_like(tokens, dtype=torch.bool)
        causal = block_mask(pad, torch.ones_like(tokens))
        positions = torch.arange(tokens.shape[1])[None]
        (ours,), _ = mixture_forward([Stream(stack, stack.embed(tokens))], attention_bias(causal, torch.float32),
                                     positions, stack.rotary_embedding())
    assert torch.allclose(ours, expected, atol=1e-4, rtol=1e-4), (ours - expected).abs().max()


# ---- the network ----------------------------------------------------------------------------


def test_prefix_cache_gives_the_joint_pass_velocity():
    vla = tiny_vla()
    x = vla.inputs(observation())
    x_t, time = torch.randn(2, 3, 4), torch.tensor([0.3, 0.9])
    with torch.no_grad():
        prefix = vla.model.encode_prefix(x.images, x.image_masks, x.tokens, x.token_mask)
        cached = vla.model.velocity(prefix, x.state, x_t, time)
        joint = vla.model.joint_velocity(x.images, x.image_masks, x.tokens, x.token_mask, x.state, x_t, time)
    assert torch.allclose(cached, joint, atol=1e-5, rtol=1e-5)


def test_instruction_is_reworded_and_padding_rows_are_left_out_of_the_loss():
    vla = tiny_vla()
    prompts = vla.processor.prompts(["reach", "other"], torch.zeros(2, 4))
    assert prompts == ["pick up the cube\n", "other\n"]
    obs, actions = observation(), torch.randn(2, 3, 4)
    noise, time = torch.randn(2, 3, 4), torch.tensor([0.5, 0.5])
    full = vla.loss(obs, actions, noise=noise, time=time, reduction="none")
    assert torch.allclose(full, vla.loss(obs, actions, noise=noise, time=time, reduction="none",
                                         action_mask=torch.ones(2, 3, dtype=torch.bool)))
    masked = vla.loss(obs, actions, noise=noise, time=time, reduction="none",
                      action_mask=torch.tensor([[True, True, False], [True, False, False]]))
    x = vla.inputs(obs)
    rows = vla.model.loss_elements(x.images, x.image_masks, x.tokens, x.token_mask, x.state,
                                   vla.processor.actions_in(actions), noise=noise, time=time).mean(-1)
    assert torch.allclose(masked, torch.stack([rows[0, :2].mean(), rows[1, 0]]))


def test_checkpoint_round_trip_gives_identical_actions(tmp_path):
    vla = tiny_vla()
    folder = save_vla(vla, tmp_path / "ckpt")
    saved = json.loads((folder / "config.json").read_text())
    assert saved["type"] == "pi0_smollm2" and saved["architecture"]["vlm"]["kind"] == "llama"
    assert (folder / "tokenizer").is_dir() and not list(tmp_path.glob(".ckpt*"))
    loaded = load_vla(folder)
    assert loaded.config == vla.config
    noise = torch.randn(2, 3, 4)
    assert torch.equal(loaded.predict_action_chunk(observation(), noise=noise),
                       vla.predict_action_chunk(observation(), noise=noise))


# ---- the RL policy --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def policy(tmp_path_factory):
    folder = save_vla(tiny_vla(), tmp_path_factory.mktemp("policy") / "ckpt")
    torch.manual_seed(0)
    return build_policy("pi0_smollm2", checkpoint=str(folder), action_dim=4, chunk=2,
                        cameras={"rgb": CAMERA}, state_key="proprio", value_hidden=8)


def env_obs(batch=2):
    raw = observation(batch)
    return {"rgb": raw[CAMERA], "proprio": raw["observation.state"], "instruction": raw["task"]}


def test_policy_act_and_evaluate_logprobs_agree(policy):
    torch.manual_seed(1)
    step = policy.act(env_obs())
    assert step.actions.shape == (2, 2, 4) and step.logprobs.shape == (2, 2) and step.values.shape == (2,)
    evaluated = policy.evaluate(env_obs(), step.actions, step.extras)
    assert torch.allclose(evaluated.logprobs, step.logprobs, atol=1e-4, rtol=1e-5)
    evaluated.logprobs.sum().backward()
    assert policy.vla.model.expert.layers[0].mlp.up_proj.weight.grad is not None
    assert policy.vla.model.vision_tower.stages[0].weight.grad is not None


def test_policy_without_instruction_field_uses_its_own(policy):
    obs = env_obs()
    del obs["instruction"]
    with pytest.raises(ValueError) as error:
        policy.inputs(obs)
    assert "instruction=..." in one_line(error)
    policy.instruction = "reach"
    try:
        assert torch.equal(policy.inputs(obs).tokens, policy.inputs({**obs, "instruction": ["reach"] * 2}).tokens)
    finally:
        policy.instruction = None


def test_policy_deterministic_act_is_the_ode_sampler(policy):
    torch.manual_seed(2)
    step = policy.act(env_obs(), deterministic=True)
    torch.manual_seed(2)
    noise = torch.randn(2, 3, 4)
    expected = policy.vla.predict_action_chunk(observation(), noise=noise)[:, :2]
    assert torch.allclose(step.actions, expected, atol=1e-5)


# ---- bad inputs -----------------------------------------------------------------------------


def test_missing_normalisation_stats_is_one_line(tmp_path):
    folder = save_vla(tiny_vla(), tmp_path / "ckpt")
    (folder / PREPROCESSOR_STATS).unlink()
    with pytest.raises(FileNotFoundError) as error:
        load_vla(folder)
    assert "normalisation stats are missing" in one_line(error)
    with pytest.raises(ValueError) as error:
        build_vla(tiny_config(), {"action": STATS["action"]}, tokenizer=TOKENIZER)
    assert "observation.state.mean" in one_line(error)


def test_wrong_image_size_is_one_line():
    vla = tiny_vla()
    with pytest.raises(ValueError) as error:
        vla.model.embed_images(torch.zeros(1, 3, 32, 32))
    assert "[B, 3, 16, 16]" in one_line(error)
    with pytest.raises(ValueError) as error:
        build_vla(tiny_config(image_resolution=(18, 18)), STATS, tokenizer=TOKENIZER)
    assert "not a multiple of 4" in one_line(error)


def test_instruction_longer_than_context_is_one_line():
    vla = tiny_vla()
    obs = observation(1)
    obs["task"] = ["open the top drawer and put the cube in it and then open it again"]
    with pytest.raises(ValueError) as error:
        vla.inputs(obs)
    assert "tokenizer_max_length 8" in one_line(error)


def test_checkpoint_of_another_family_is_one_line(tmp_path):
    folder = save_vla(tiny_vla(), tmp_path / "ckpt")
    with pytest.raises(ValueError) as error:
        load_vla(folder, family="pi0")
    assert "'pi0_smollm2' checkpoint, not 'pi0'" in one_line(error)
    with pytest.raises(ValueError) as error:
        build_policy("pi0_smollm2", checkpoint=str(FIXTURES / "pi0"), action_dim=3,
                     tokenizer=str(TOKENIZER))
    assert "'pi0' checkpoint, not 'pi0_smollm2'" in one_line(error)
    with pytest.raises(ValueError) as error:
        build_policy("pi0", checkpoint=tiny_vla(), action_dim=4)
    assert "'pi0_smollm2' model, not 'pi0'" in one_line(error)


def test_bad_sizes_are_one_line():
    with pytest.raises(ValueError) as error:
        SmolVLASpec(language_layers=31)
    assert "SmolLM2-135M has 30 layers" in one_line(error)
    with pytest.raises(ValueError) as error:
        SmolVLASpec(expert_width=100)
    assert "multiple of 18" in one_line(error)
    with pytest.raises(ValueError) as error:
        VLAArchitecture(vlm=TINY_VLM, expert=LlamaSpec(width=18, depth=2, mlp_dim=24, num_heads=3, num_kv_heads=3,
                                                       head_dim=8))
    assert "same heads, kv heads and head_dim" in one_line(error)
