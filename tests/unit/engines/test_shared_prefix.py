"""Prompt packing (``share_prompt_prefix``): rows sharing a prompt train as one packed sequence.

The claim is exactness: every scored token sees the same keys at the same positions as in its own
row, so log-probs, entropies and the update equal the plain path's. The references here are the
float64, one-sequence-at-a-time loop of ``test_fsdp`` and the engine with packing switched off.
"""

from __future__ import annotations

import pytest
import torch
from transformers import LlamaConfig

from infinirl.data.batch import RESPONSE_MASK, pack_sequences
from infinirl.engines.fsdp import FSDPTrainEngine
from infinirl.engines.shared_prefix import pack_by_prompt, supports_packed_masks
from tests.unit.engines.test_fsdp import (
    VOCAB,
    assert_weights_close,
    config,
    exported,
    global_token_loss,
    one_rank_group,  # noqa: F401  (module-scoped autouse fixture: a one-rank gloo group)
    reference_logprobs,
    reference_model,
    tiny_llama,
)


def grouped_batch(seed: int, groups: int = 3, group_size: int = 4):
    """GRPO layout: ``groups`` prompts of different lengths, each sampled ``group_size`` times,
    responses of ragged length (one of them empty), plus one prompt that appears once."""
    gen = torch.Generator().manual_seed(seed)
    prompts, responses = [], []
    for g in range(groups):
        prompt = torch.randint(1, VOCAB, (3 + 2 * g,), generator=gen).tolist()
        for k in range(group_size):
            length = 0 if (g, k) == (1, 2) else 1 + (k * 3 + g) % 6
            prompts.append(prompt)
            responses.append(torch.randint(1, VOCAB, (length,), generator=gen).tolist())
    prompts.append(torch.randint(1, VOCAB, (4,), generator=gen).tolist())
    responses.append(torch.randint(1, VOCAB, (5,), generator=gen).tolist())
    return pack_sequences(prompts, responses, pad_token_id=0)


def test_rows_sharing_a_prompt_become_one_packed_row_without_padding():
    batch = grouped_batch(seed=0)
    packed = pack_by_prompt(batch["input_ids"], batch["attention_mask"], batch.get("position_ids", None),
                            batch[RESPONSE_MASK])
    assert packed.input_ids.shape[0] == 4  # 3 shared prompts + 1 single one
    lengths = batch["prompt_lengths"] + batch["response_lengths"]
    assert packed.input_ids.numel() < lengths.sum()  # fewer tokens than even the unpadded rows
    assert packed.target.numel() == int(batch[RESPONSE_MASK].sum())  # every response token scored once
    torch.testing.assert_close(packed.target, batch["input_ids"][packed.row, packed.column])


def test_long_groups_are_cut_into_several_packed_rows():
    batch = grouped_batch(seed=0)
    ids, mask, responses = batch["input_ids"], batch["attention_mask"], batch[RESPONSE_MASK]
    whole = pack_by_prompt(ids, mask, None, responses)
    cut = pack_by_prompt(ids, mask, None, responses, max_packed_tokens=12)
    assert cut.input_ids.shape[0] > whole.input_ids.shape[0]
    assert cut.input_ids.shape[1] <= max(12, int((batch["prompt_lengths"] + batch["response_lengths"]).max()))
    for field in ("target", "row", "column"):  # the same tokens scored, just in more rows
        torch.testing.assert_close(getattr(cut, field), getattr(whole, field))


@pytest.mark.parametrize(("temperature", "max_packed_tokens"), [(1.0, 2048), (0.7, 2048), (1.0, 12)])
def test_packed_scoring_equals_the_float64_row_by_row_reference(temperature, max_packed_tokens):
    batch = grouped_batch(seed=1)
    engine = FSDPTrainEngine(tiny_llama, config(micro_batch_size=16, temperature=temperature,
                                                max_packed_tokens=max_packed_tokens))
    assert engine._shares_prompt_prefix
    logprobs, entropy = engine.compute_logprobs(batch, with_entropy=True)
    ref_lp, ref_ent = reference_logprobs(reference_model(exported(engine)), batch, temperature)
    mask = batch[RESPONSE_MASK].bool()
    torch.testing.assert_close(logprobs.double()[mask], ref_lp[mask], atol=1e-5, rtol=0)
    torch.testing.assert_close(entropy.double()[mask], ref_ent[mask], atol=1e-5, rtol=0)
    assert logprobs[~mask].abs().sum() == 0 and entropy[~mask].abs().sum() == 0


def test_without_a_response_mask_every_token_after_the_first_is_scored():
    batch = grouped_batch(seed=2)
    del batch[RESPONSE_MASK]
    engine = FSDPTrainEngine(tiny_llama, config(micro_batch_size=16))
    logprobs, _ = engine.compute_logprobs(batch)
    ref_lp, _ = reference_logprobs(reference_model(exported(engine)), batch, 1.0)
    torch.testing.assert_close(logprobs.double(), ref_lp, atol=1e-5, rtol=0)


@pytest.mark.parametrize("micro_batch_size", [16, 3])
def test_a_packed_training_step_equals_the_plain_one(micro_batch_size):
    """Same weights after two steps whether rows are packed or not, whatever the micro-batching
    (3 splits groups across micro-batches: packing then only merges rows within each)."""
    batch = grouped_batch(seed=3)
    loss_fn = global_token_loss(float(batch[RESPONSE_MASK].sum()))
    plain = FSDPTrainEngine(tiny_llama, config(micro_batch_size=micro_batch_size, share_prompt_prefix=False))
    packed = FSDPTrainEngine(tiny_llama, config(micro_batch_size=micro_batch_size))
    for engine in (plain, packed):
        for _ in range(2):
            engine.train_step(batch, loss_fn)
    assert_weights_close(exported(packed), exported(plain), atol=1e-6)
    assert not torch.equal(exported(plain)["lm_head.weight"], tiny_llama_weights()["lm_head.weight"])


def tiny_llama_weights():
    torch.manual_seed(0)
    return tiny_llama().state_dict()


def test_sliding_window_models_are_not_packed():
    assert supports_packed_masks(LlamaConfig())
    assert not supports_packed_masks(LlamaConfig(layer_types=["sliding_attention", "full_attention"],
                                                 num_hidden_layers=2))

    class Windowed:
        sliding_window, use_sliding_window = 4096, True

    class WindowOff:
        sliding_window, use_sliding_window = 4096, False

    assert not supports_packed_masks(Windowed())
    assert supports_packed_masks(WindowOff())

    class Flash:
        _attn_implementation = "flash_attention_2"

    assert not supports_packed_masks(Flash())


@pytest.mark.parametrize("overrides", [{"score_prompts": True}, {"activation_checkpointing": True},
                                       {"share_prompt_prefix": False}])
def test_packing_is_off_where_it_cannot_apply(overrides):
    assert not FSDPTrainEngine(tiny_llama, config(**overrides))._shares_prompt_prefix
