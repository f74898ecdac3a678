"""LoRA on the top decoder layers only: the cheap-trainer option of the default GRPO job.

The point of ``lora.top_layers`` is that backpropagation stops below the lowest adapted layer, so
these tests check (1) only those layers get adapters, (2) autograd really does not reach the
layers below (their activations need no gradient), and (3) the exported weights stay exact.
"""

from __future__ import annotations

import pytest
import torch
import torch.distributed as dist
from transformers import LlamaConfig, LlamaForCausalLM

from infinirl.data.batch import RESPONSE_MASK, pack_sequences
from infinirl.engines.fsdp import FSDPTrainEngine, init_distributed
from infinirl.engines.train_base import LoraSettings, TrainEngineConfig


def four_layer_llama() -> LlamaForCausalLM:
    torch.manual_seed(0)
    return LlamaForCausalLM(LlamaConfig(vocab_size=64, hidden_size=32, intermediate_size=64, num_hidden_layers=4,
                                        num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=64))


@pytest.fixture(scope="module", autouse=True)
def one_rank_group():
    torch.set_num_threads(1)
    created = init_distributed()
    yield
    if created:
        dist.destroy_process_group()


def batch():
    gen = torch.Generator().manual_seed(3)
    prompts = [torch.randint(1, 64, (n,), generator=gen).tolist() for n in (3, 5, 4, 2)]
    responses = [torch.randint(1, 64, (n,), generator=gen).tolist() for n in (4, 2, 3, 5)]
    return pack_sequences(prompts, responses, pad_token_id=0)


def loss_fn(micro, logprobs, entropy):
    mask = micro[RESPONSE_MASK]
    loss = -(logprobs * mask).sum() / 14.0
    return loss, {"pg_loss": loss.detach()}


def engine(top_layers: int) -> FSDPTrainEngine:
    lora = LoraSettings(r=4, alpha=8, target_modules="all-linear", top_layers=top_layers)
    return FSDPTrainEngine(four_layer_llama, TrainEngineConfig(lora=lora, lr=2e-2, eps=1e-3, micro_batch_size=4,
                                                               grad_clip=None, seed=0, device="cpu"))


def test_only_the_top_layers_get_adapters_and_train():
    eng = engine(top_layers=2)
    names = [n for n, p in eng.model.named_parameters() if p.requires_grad]
    layers = {int(n.split(".layers.")[1].split(".")[0]) for n in names}
    assert layers == {2, 3}
    projections = {"q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj"}
    assert {n.split(".")[-4] for n in names} == projections
    before = {n: t.clone() for n, t in eng.state_dict_for_sync()}
    losses = [eng.train_step(batch(), loss_fn)["train/loss"] for _ in range(4)]
    assert losses[-1] < losses[0]
    after = dict(eng.state_dict_for_sync())
    changed = {n for n in before if not torch.equal(before[n], after[n])}
    assert changed and all(".layers.2." in n or ".layers.3." in n for n in changed), sorted(changed)


def test_a_changed_only_export_is_the_merged_adapted_layers_of_the_full_one():
    """``state_dict_for_sync(changed_only=True)``: exactly the weights an update can change (the
    top layers' adapted projections, adapters merged), equal to the full export's; embeddings,
    norms and the layers below stay out."""
    eng = engine(top_layers=2)
    for _ in range(2):
        eng.train_step(batch(), loss_fn)
    full = dict(eng.state_dict_for_sync())
    changing = dict(eng.state_dict_for_sync(changed_only=True))
    projections = ("q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj")
    module = {"q_proj": "self_attn", "k_proj": "self_attn", "v_proj": "self_attn", "o_proj": "self_attn"}
    assert set(changing) == {f"model.layers.{layer}.{module.get(p, 'mlp')}.{p}.weight"
                             for layer in (2, 3) for p in projections}
    assert all(torch.equal(changing[name], full[name]) for name in changing)
    initial = dict(engine(top_layers=2).state_dict_for_sync())
    assert {n for n in full if not torch.equal(full[n], initial[n])} <= set(changing)  # nothing else moved


def test_backward_does_not_reach_the_frozen_layers():
    eng = engine(top_layers=1)
    seen: list[bool] = []
    hooks = [layer.register_forward_hook(lambda mod, args, out: seen.append(
        (out[0] if isinstance(out, tuple) else out).requires_grad))
        for layer in eng.model.base_model.model.model.layers]
    eng.train_step(batch(), loss_fn)
    for h in hooks:
        h.remove()
    assert seen == [False, False, False, True], seen


def test_top_layers_out_of_range_is_a_clear_error():
    with pytest.raises(ValueError, match="top_layers=9.*4 decoder layers"):
        engine(top_layers=9)


def test_a_target_tied_to_the_input_embeddings_is_refused():
    """A LoRA ``lm_head`` on a tied-embedding model: its merged export would also change the
    rollout's input embeddings, which the trainer's adapter leaves alone."""
    from infinirl.engines.lora import apply_lora

    torch.manual_seed(0)
    tied = LlamaForCausalLM(LlamaConfig(vocab_size=64, hidden_size=32, intermediate_size=64, num_hidden_layers=1,
                                        num_attention_heads=4, num_key_value_heads=2, tie_word_embeddings=True))
    with pytest.raises(ValueError, match=r"LoRA target '.*lm_head' shares its weight with the input embeddings"):
        apply_lora(tied, LoraSettings(r=4, alpha=8, target_modules=["q_proj", "lm_head"]))
    untied = four_layer_llama()  # tie_word_embeddings off: an adapted lm_head merges into its own weight
    apply_lora(untied, LoraSettings(r=4, alpha=8, target_modules=["q_proj", "lm_head"]))

