"""Log-probs / entropies from logits against a float64, one-token-at-a-time reference."""

import math

import pytest
import torch

from infinirl.engines.logprobs import aligned_logprobs, token_logprobs


def reference_aligned(logits, input_ids, attention_mask, temperature):
    """The definition, spelled out: loops, float64, ``log_softmax`` of the previous position."""
    batch, length, _ = logits.shape
    logprobs = torch.zeros(batch, length, dtype=torch.float64)
    entropy = torch.zeros(batch, length, dtype=torch.float64)
    for b in range(batch):
        for t in range(1, length):
            if not attention_mask[b, t]:
                continue
            log_p = torch.log_softmax(logits[b, t - 1].double() / temperature, dim=-1)
            logprobs[b, t] = log_p[input_ids[b, t]]
            entropy[b, t] = -(log_p.exp() * log_p).sum()
    return logprobs, entropy


def ragged_batch(seed=0, batch=4, length=9, vocab=37):
    gen = torch.Generator().manual_seed(seed)
    logits = torch.randn(batch, length, vocab, generator=gen) * 3
    input_ids = torch.randint(0, vocab, (batch, length), generator=gen)
    lengths = torch.tensor([length, 5, 1, 7])[:batch]
    attention_mask = (torch.arange(length)[None, :] < lengths[:, None]).long()
    return logits, input_ids, attention_mask


@pytest.mark.parametrize("chunk_tokens", [1, 5, 4096])
@pytest.mark.parametrize("temperature", [1.0, 0.7])
def test_aligned_logprobs_and_entropy_match_reference(chunk_tokens, temperature):
    logits, input_ids, attention_mask = ragged_batch()
    logprobs, entropy = aligned_logprobs(
        logits, input_ids, attention_mask, temperature, chunk_tokens, with_entropy=True
    )
    ref_logprobs, ref_entropy = reference_aligned(logits, input_ids, attention_mask, temperature)
    assert logprobs.dtype == entropy.dtype == torch.float32
    assert logprobs.shape == input_ids.shape
    torch.testing.assert_close(logprobs.double(), ref_logprobs, atol=1e-5, rtol=0)
    torch.testing.assert_close(entropy.double(), ref_entropy, atol=1e-5, rtol=0)
    # Position 0 has no context and padded positions score nothing.
    assert (logprobs[:, 0] == 0).all() and (logprobs[attention_mask == 0] == 0).all()


def test_entropy_is_skipped_unless_requested():
    logits, input_ids, attention_mask = ragged_batch()
    _, entropy = aligned_logprobs(logits, input_ids, attention_mask)
    assert entropy is None


def test_uniform_logits_give_log_vocab():
    vocab = 16
    logprobs, entropy = token_logprobs(
        torch.zeros(3, vocab), torch.tensor([0, 5, 15]), with_entropy=True
    )
    torch.testing.assert_close(logprobs, torch.full((3,), -math.log(vocab)))
    torch.testing.assert_close(entropy, torch.full((3,), math.log(vocab)))


def test_bf16_logits_are_upcast_before_softmax():
    logits, input_ids, attention_mask = ragged_batch()
    low = logits.bfloat16()
    logprobs, _ = aligned_logprobs(low, input_ids, attention_mask)
    ref, _ = reference_aligned(low.double(), input_ids, attention_mask, 1.0)
    assert logprobs.dtype == torch.float32
    torch.testing.assert_close(logprobs.double(), ref, atol=1e-5, rtol=0)


def test_chunked_checkpointed_gradient_matches_plain_log_softmax():
    logits, input_ids, attention_mask = ragged_batch()
    weights = torch.randn(input_ids.shape, generator=torch.Generator().manual_seed(3))

    chunked = logits.clone().requires_grad_(True)
    lp, ent = aligned_logprobs(
        chunked, input_ids, attention_mask, 0.9, chunk_tokens=4, with_entropy=True
    )
    ((lp + 0.1 * ent) * weights).sum().backward()

    plain = logits.double().clone().requires_grad_(True)
    log_p = torch.log_softmax(plain[:, :-1] / 0.9, dim=-1)
    ref_lp = log_p.gather(-1, input_ids[:, 1:, None]).squeeze(-1)
    ref_ent = -(log_p.exp() * log_p).sum(-1)
    mask = attention_mask[:, 1:].double()
    ((ref_lp + 0.1 * ref_ent) * mask * weights[:, 1:]).sum().backward()

    torch.testing.assert_close(chunked.grad.double(), plain.grad, atol=1e-5, rtol=0)


def test_shape_and_temperature_errors():
    with pytest.raises(ValueError, match="temperature"):
        token_logprobs(torch.zeros(2, 4), torch.zeros(2, dtype=torch.long), temperature=0.0)
    with pytest.raises(ValueError, match="do not match"):
        token_logprobs(torch.zeros(2, 4), torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="do not match"):
        aligned_logprobs(torch.zeros(2, 5, 4), torch.zeros(2, 6, dtype=torch.long))
