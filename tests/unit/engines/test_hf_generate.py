"""HFGenerateEngine against slow references, on a tiny random Llama (no hub, < 1 s per test)."""

from collections import Counter

import pytest
import torch
from transformers import DynamicCache

from infinirl.data.batch import (
    ATTENTION_MASK,
    INPUT_IDS,
    POSITION_IDS,
    RESPONSE_MASK,
    ROLLOUT_LOGPROBS,
    pack_sequences,
)
from infinirl.engines.base import SamplingParams
from infinirl.engines.hf_generate import HFGenerateEngine
from infinirl.engines.kv_cache import PreallocatedKVLayer, cache_keyword, new_kv_cache
from infinirl.engines.sampling import excluded_tokens, sample_from_weights
from infinirl.models.hf_causal_lm import tiny_causal_lm

# Different lengths, so batched prompts really are left-padded.
PROMPTS = [[5, 6, 7, 8, 9, 10, 11], [20, 21], [30, 31, 32, 33]]


@pytest.fixture(scope="module", autouse=True)
def single_thread(one_torch_thread):
    """Every test here runs on one torch thread (see the fixture)."""


@pytest.fixture(scope="module")
def tiny(tiny_byte_llama):
    return tiny_byte_llama


@pytest.fixture
def engine(tiny):
    model, tokenizer = tiny
    # The tiny random model rarely emits EOS; tests pass stop ids explicitly where they need them.
    return HFGenerateEngine(model, tokenizer, max_batch_size=64, eos_token_ids=[])


def recompute_logprobs(model, results, temperature: float, pad_token_id: int) -> torch.Tensor:
    """Slow reference: one full forward over the trainer's packed layout, log_softmax(logits/T)."""
    batch = pack_sequences(
        [r.prompt_ids for r in results],
        [r.response_ids for r in results],
        pad_token_id,
        [r.response_logprobs for r in results],
    )
    with torch.no_grad():
        logits = model(
            input_ids=batch[INPUT_IDS],
            attention_mask=batch[ATTENTION_MASK],
            position_ids=batch[POSITION_IDS],
        ).logits.float()
    logprobs = torch.log_softmax(logits[:, :-1] / temperature, dim=-1)
    token_logprobs = logprobs.gather(-1, batch[INPUT_IDS][:, 1:, None]).squeeze(-1)
    aligned = torch.zeros_like(batch[ROLLOUT_LOGPROBS])
    aligned[:, 1:] = token_logprobs  # batch.py convention: entry t scores input_ids[t]
    mask = batch[RESPONSE_MASK].bool()
    return aligned[mask], batch[ROLLOUT_LOGPROBS][mask]


@pytest.mark.parametrize(
    "sampling",
    [
        SamplingParams(n=2, max_new_tokens=12, temperature=1.0, seed=3),
        SamplingParams(n=2, max_new_tokens=12, temperature=0.7, top_k=20, top_p=0.9, seed=4),
        SamplingParams(max_new_tokens=12, greedy=True),
    ],
    ids=["T=1", "T=0.7+topk+topp", "greedy"],
)
def test_logprobs_equal_full_forward_recomputation(tiny, engine, sampling):
    model, tokenizer = tiny
    results = engine.generate(PROMPTS, sampling)
    assert all(len(r.response_logprobs) == len(r.response_ids) == 12 for r in results)
    reference, returned = recompute_logprobs(
        model, results, sampling.logprob_temperature, tokenizer.pad_token_id
    )
    torch.testing.assert_close(returned, reference, atol=1e-5, rtol=0)


def test_greedy_is_deterministic_and_independent_of_padding_and_micro_batching(tiny, engine):
    model, tokenizer = tiny
    greedy = SamplingParams(max_new_tokens=10, greedy=True)
    batched = engine.generate(PROMPTS, greedy)
    assert engine.generate(PROMPTS, greedy) == batched
    alone = [engine.generate([p], greedy)[0].response_ids for p in PROMPTS]
    assert [r.response_ids for r in batched] == alone
    small = HFGenerateEngine(model, tokenizer, max_batch_size=2, eos_token_ids=[])
    assert [r.response_ids for r in small.generate(PROMPTS, greedy)] == alone


def test_greedy_picks_the_argmax(tiny, engine):
    model, _ = tiny
    result = engine.generate([PROMPTS[0]], SamplingParams(max_new_tokens=1, greedy=True))[0]
    with torch.no_grad():
        logits = model(input_ids=torch.tensor([PROMPTS[0]])).logits[0, -1]
    assert result.response_ids == [int(logits.argmax())]


def test_same_seed_same_samples_and_other_seed_differs(engine):
    def sample(seed):
        sampling = SamplingParams(n=3, max_new_tokens=8, seed=seed)
        return [r.response_ids for r in engine.generate(PROMPTS, sampling)]

    assert sample(7) == sample(7)
    assert sample(7) != sample(8)


def test_global_torch_seed_makes_unseeded_sampling_reproducible(engine):
    torch.manual_seed(123)
    first = engine.generate(PROMPTS, SamplingParams(max_new_tokens=8))
    torch.manual_seed(123)
    assert engine.generate(PROMPTS, SamplingParams(max_new_tokens=8)) == first


def test_results_are_prompt_major_with_n_samples_each(engine):
    results = engine.generate(PROMPTS, SamplingParams(n=3, max_new_tokens=4, seed=0))
    assert [(r.prompt_index, r.sample_index) for r in results] == [
        (p, s) for p in range(len(PROMPTS)) for s in range(3)
    ]
    assert [r.prompt_ids for r in results] == [p for p in PROMPTS for _ in range(3)]
    # Samples of one prompt share a prefill but must still be independent draws.
    assert len({tuple(r.response_ids) for r in results[:3]}) > 1


def test_micro_batches_split_groups_without_changing_the_layout(tiny):
    model, tokenizer = tiny
    engine = HFGenerateEngine(model, tokenizer, max_batch_size=4, eos_token_ids=[])
    results = engine.generate(PROMPTS, SamplingParams(n=3, max_new_tokens=6, seed=1))
    assert len(results) == 9
    assert [r.prompt_ids for r in results] == [p for p in PROMPTS for _ in range(3)]
    reference, returned = recompute_logprobs(model, results, 1.0, tokenizer.pad_token_id)
    torch.testing.assert_close(returned, reference, atol=1e-5, rtol=0)


def test_sampling_frequencies_follow_returned_probabilities(engine):
    """Ancestral sampling check: empirical first-token frequencies ~ exp(returned log-prob)."""
    draws = 3000
    results = engine.generate([PROMPTS[1]], SamplingParams(n=draws, max_new_tokens=1, seed=0))
    counts = Counter(r.response_ids[0] for r in results)
    prob = {r.response_ids[0]: torch.tensor(r.response_logprobs[0]).exp().item() for r in results}
    for token, count in counts.most_common(5):
        expected = prob[token] * draws
        assert abs(count - expected) < 5 * expected**0.5 + 5, (token, count, expected)


def test_top_k_1_and_tiny_top_p_reduce_to_greedy(engine):
    greedy = engine.generate(PROMPTS, SamplingParams(max_new_tokens=8, greedy=True))
    top_k_1 = engine.generate(PROMPTS, SamplingParams(max_new_tokens=8, top_k=1, seed=0))
    top_p_0 = engine.generate(PROMPTS, SamplingParams(max_new_tokens=8, top_p=1e-6, seed=0))
    ids = [r.response_ids for r in greedy]
    assert [r.response_ids for r in top_k_1] == ids
    assert [r.response_ids for r in top_p_0] == ids


def kept(probs, top_k, top_p):
    return (~excluded_tokens(torch.tensor([probs]), top_k, top_p)).int().tolist()[0]


def test_top_k_top_p_keep_the_expected_sets():
    probs = [0.5, 0.3, 0.15, 0.05]
    assert kept(probs, 2, 1.0) == [1, 1, 0, 0]
    # 0.5 < 0.7 <= 0.5 + 0.3: the nucleus is the first two tokens.
    assert kept(probs, 0, 0.7) == [1, 1, 0, 0]
    assert kept(probs, 0, 0.85) == [1, 1, 1, 0]
    # top-p runs on the top-3 set renormalised: 0.5/0.95 = 0.53 >= 0.5.
    assert kept(probs, 3, 0.5) == [1, 0, 0, 0]
    assert kept(probs, 3, 0.6) == [1, 1, 0, 0]
    assert excluded_tokens(torch.tensor([probs]), 0, 1.0) is None


def brute_force_nucleus(probs: torch.Tensor, top_p: float) -> torch.Tensor:
    keep = torch.zeros_like(probs, dtype=torch.bool)
    for row in range(probs.shape[0]):
        mass = 0.0
        for token in torch.argsort(probs[row], descending=True).tolist():
            if mass >= top_p:
                break
            keep[row, token] = True
            mass += probs[row, token].item()
    return keep


def test_nucleus_is_exact_for_narrow_and_wide_distributions():
    """Peaked rows are solved among the top 64 tokens, flat rows by the full-sort fallback."""
    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(6, 500, generator=gen, dtype=torch.float64)
    logits[:3] *= 8.0  # peaked: nucleus of a few tokens
    logits[3:] *= 0.1  # nearly flat: nucleus of hundreds of tokens
    probs = torch.softmax(logits, dim=-1)
    for top_p in (0.3, 0.9):
        assert torch.equal(~excluded_tokens(probs, 0, top_p), brute_force_nucleus(probs, top_p))
    assert (~excluded_tokens(probs, 0, 0.9))[3:].sum(-1).min() > 64


def test_sample_from_weights_never_picks_zero_weight_and_matches_frequencies():
    gen = torch.Generator().manual_seed(0)
    weights = torch.tensor([[0.0, 2.0, 0.0, 6.0, 0.0]]).repeat(20_000, 1)
    counts = torch.bincount(sample_from_weights(weights, gen), minlength=5).tolist()
    assert counts[0] == counts[2] == counts[4] == 0
    assert abs(counts[3] / 20_000 - 0.75) < 0.02


def test_sample_from_weights_handles_u_rounding_up_to_the_total(monkeypatch):
    # rand() < 1, but u * total can still round to total; simulate that worst case.
    monkeypatch.setattr(torch, "rand", lambda shape, **kw: torch.ones(shape, dtype=kw["dtype"]))
    weights = torch.tensor([[1.0, 3.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]])
    assert sample_from_weights(weights, None).tolist() == [1, 3]


def test_preallocated_cache_matches_transformers_dynamic_cache(tiny):
    """Same logits step by step as transformers' own cache, including batch selection."""
    model, _ = tiny
    prompt = torch.tensor([PROMPTS[0], PROMPTS[0][::-1]])
    ours, theirs = new_kv_cache(model, capacity=12), DynamicCache(config=model.config)
    assert all(isinstance(layer, PreallocatedKVLayer) for layer in ours.layers)
    key = cache_keyword(model)
    with torch.no_grad():
        for cache in (ours, theirs):
            model(input_ids=prompt, use_cache=True, **{key: cache})
            cache.batch_select_indices(torch.tensor([1, 0, 1]))
        step = torch.tensor([[40], [41], [42]])
        for _ in range(3):
            a = model(input_ids=step, use_cache=True, **{key: ours}).logits
            b = model(input_ids=step, use_cache=True, **{key: theirs}).logits
            torch.testing.assert_close(a, b, atol=1e-6, rtol=0)
    assert ours.get_seq_length() == theirs.get_seq_length() == len(PROMPTS[0]) + 3


def test_cache_keyword_follows_the_forward_signature():
    class Renamed(torch.nn.Module):  # transformers >= 5.2x
        def forward(self, input_ids, cache=None, **kwargs):
            return input_ids

    class Original(torch.nn.Module):  # transformers 4.x
        def forward(self, input_ids, past_key_values=None, **kwargs):
            return input_ids

    assert cache_keyword(Renamed()) == "cache"
    assert cache_keyword(Original()) == "past_key_values"
    assert cache_keyword(torch.compile(Renamed())) == "cache"  # looks through torch.compile's wrapper


def test_generation_passes_the_cache_without_deprecation_warnings(engine, recwarn):
    """A deprecated cache keyword warns on every forward: dozens of lines per rollout, per rank."""
    import warnings

    warnings.simplefilter("always")
    engine.generate(PROMPTS[:2], SamplingParams(max_new_tokens=4, n=2, seed=0))
    assert not [w for w in recwarn if "past_key_values" in str(w.message)], [str(w.message) for w in recwarn]


def test_stop_token_truncates_and_is_kept(tiny, engine):
    model, tokenizer = tiny
    free_run = engine.generate(PROMPTS, SamplingParams(max_new_tokens=10, greedy=True))
    stop_token = free_run[0].response_ids[3]
    first_hit = free_run[0].response_ids.index(stop_token)
    stopped = engine.generate(
        PROMPTS, SamplingParams(max_new_tokens=10, greedy=True, stop_token_ids=[stop_token])
    )
    assert stopped[0].response_ids == free_run[0].response_ids[: first_hit + 1]
    assert stopped[0].finish_reason == "stop"
    assert len(stopped[0].response_logprobs) == first_hit + 1
    # The same token as the engine's EOS behaves the same, unless ignore_eos.
    eos_engine = HFGenerateEngine(model, tokenizer, eos_token_ids=[stop_token])
    greedy = SamplingParams(max_new_tokens=10, greedy=True)
    assert eos_engine.generate(PROMPTS, greedy)[0].response_ids == stopped[0].response_ids
    ignoring = SamplingParams(max_new_tokens=10, greedy=True, ignore_eos=True)
    assert eos_engine.generate(PROMPTS, ignoring)[0].response_ids == free_run[0].response_ids
    # Rows that stop early leave the batch; the others must be unaffected.
    for stopped_row, free_row in zip(stopped, free_run):
        n = len(stopped_row.response_ids)
        assert stopped_row.response_ids == free_row.response_ids[:n]
        expected = free_row.response_logprobs[:n]
        assert stopped_row.response_logprobs == pytest.approx(expected, abs=1e-5)


def test_stop_string_truncates_after_the_completing_token(tiny, engine):
    _, tokenizer = tiny
    free_run = engine.generate([PROMPTS[0]], SamplingParams(max_new_tokens=16, greedy=True))[0]
    ids = free_run.response_ids
    stop = tokenizer.decode(ids[4:6])
    expected_len = next(
        j + 1 for j in range(len(ids)) if stop in tokenizer.decode(ids[: j + 1])
    )
    stopped = engine.generate(
        [PROMPTS[0]], SamplingParams(max_new_tokens=16, greedy=True, stop_strings=[stop])
    )[0]
    assert stopped.response_ids == ids[:expected_len]
    assert stopped.finish_reason == "stop"
    assert stopped.extra["stop_string"] == stop


def test_stop_strings_without_tokenizer_fail_clearly(tiny):
    model, _ = tiny
    engine = HFGenerateEngine(model, tokenizer=None, eos_token_ids=[])
    with pytest.raises(ValueError, match="need a tokenizer"):
        engine.generate(PROMPTS, SamplingParams(stop_strings=["\n"]))


def test_max_new_tokens_gives_length_finish(engine):
    results = engine.generate(PROMPTS, SamplingParams(n=2, max_new_tokens=5, seed=0))
    assert all(len(r.response_ids) == 5 and r.finish_reason == "length" for r in results)


def test_load_weights_is_bit_exact_and_versioned(tiny):
    model, tokenizer = tiny
    engine = HFGenerateEngine(tiny_causal_lm(tokenizer="byte", seed=1)[0], tokenizer)
    assert engine.weight_version == 0
    # named_parameters() drops the tied lm_head alias: sending either name is enough.
    engine.load_weights(model.named_parameters(), version=5)
    assert engine.weight_version == 5
    ours, theirs = engine.model.state_dict(), model.state_dict()
    assert ours.keys() == theirs.keys()
    assert all(torch.equal(ours[k], theirs[k]) for k in ours)
    greedy = SamplingParams(max_new_tokens=6, greedy=True)
    reference = HFGenerateEngine(model, tokenizer).generate(PROMPTS, greedy)
    results = engine.generate(PROMPTS, greedy)
    assert [r.response_ids for r in results] == [r.response_ids for r in reference]
    assert all(r.weight_version == 5 for r in results)


def test_load_weights_rejects_unknown_missing_and_misshaped(tiny):
    model, tokenizer = tiny
    engine = HFGenerateEngine(tiny_causal_lm(tokenizer="byte", seed=1)[0], tokenizer)
    named = dict(model.named_parameters())
    with pytest.raises(KeyError, match="module.model.norm.weight"):
        engine.load_weights([("module.model.norm.weight", named["model.norm.weight"])], 1)
    with pytest.raises(ValueError, match="shape"):
        engine.load_weights([("model.norm.weight", torch.zeros(3))], 1)
    with pytest.raises(ValueError, match="not sent"):
        engine.load_weights([("model.norm.weight", named["model.norm.weight"])], 1)
    assert engine.weight_version == 0


def test_changed_only_loads_follow_a_full_load_and_keep_the_rest(tiny):
    """A changed-only sync is refused until the engine holds a full one (the weights it leaves out
    would be the engine's own, maybe not the trainer's); after it, the sent weights are copied, the
    rest kept, and the version adopted; later ones must send the same weights as the first."""
    model, tokenizer = tiny
    engine = HFGenerateEngine(tiny_causal_lm(tokenizer="byte", seed=1)[0], tokenizer)
    norm = ("model.norm.weight", torch.full_like(dict(model.named_parameters())["model.norm.weight"], 0.5))
    with pytest.raises(ValueError, match=r"has not loaded a full set .* weight_version stays 0"):
        engine.load_weights([norm], version=1, changed_only=True)
    engine.load_weights(model.named_parameters(), version=1)
    engine.load_weights([norm], version=2, changed_only=True)
    assert engine.weight_version == 2
    ours, theirs = engine.model.state_dict(), model.state_dict()
    assert torch.equal(ours["model.norm.weight"], norm[1])
    assert all(torch.equal(ours[k], theirs[k]) for k in ours if k != "model.norm.weight")
    other = ("model.embed_tokens.weight", theirs["model.embed_tokens.weight"])
    for sent in ([other], [norm, other], []):  # what training changes does not change between syncs
        with pytest.raises(ValueError, match=r"the first changed-only sync 1; .* version stays 2"):
            engine.load_weights(sent, version=3, changed_only=True)
    engine.load_weights([norm], version=3, changed_only=True)
    assert engine.weight_version == 3


def test_a_load_that_fails_partway_stops_generation_until_a_load_repairs_it(tiny):
    """Tensors copied before a load failed leave two versions mixed under the old version's stamp:
    generate refuses to run on them, naming the failed version, until a load rewrites what the
    failed one may have touched (a full one after a failed full load)."""
    model, tokenizer = tiny
    engine = HFGenerateEngine(tiny_causal_lm(tokenizer="byte", seed=1)[0], tokenizer)
    engine.load_weights(model.named_parameters(), version=1)
    greedy = SamplingParams(max_new_tokens=3, greedy=True)
    engine.generate(PROMPTS, greedy)

    def breaks_after_the_first(named):
        named = iter(named)
        yield next(named)
        raise ConnectionError("bucket 2 lost on its way")

    newer = tiny_causal_lm(tokenizer="byte", seed=2)[0]
    with pytest.raises(ConnectionError):
        engine.load_weights(breaks_after_the_first(newer.named_parameters()), version=2)
    assert engine.weight_version == 1
    with pytest.raises(RuntimeError, match="loading weights version 2 failed after copying some"):
        engine.generate(PROMPTS, greedy)
    norm = ("model.norm.weight", dict(newer.named_parameters())["model.norm.weight"])
    with pytest.raises(ValueError, match="has not loaded a full set"):  # the rest may not be the trainer's
        engine.load_weights([norm], version=2, changed_only=True)
    with pytest.raises(KeyError, match="unknown weight name"):  # nothing copied: still torn by version 2
        engine.load_weights([("nope", norm[1])], version=3)
    with pytest.raises(RuntimeError, match="version 2 failed"):
        engine.generate(PROMPTS, greedy)
    engine.load_weights(newer.named_parameters(), version=3)
    assert all(r.weight_version == 3 for r in engine.generate(PROMPTS, greedy))

    # A changed-only load that fails partway is repaired by the next changed-only one.
    engine.load_weights([norm], version=4, changed_only=True)
    with pytest.raises(ConnectionError):
        engine.load_weights(breaks_after_the_first([norm, norm]), version=5, changed_only=True)
    with pytest.raises(RuntimeError, match="version 5 failed"):
        engine.generate(PROMPTS, greedy)
    engine.load_weights([norm], version=6, changed_only=True)
    assert all(r.weight_version == 6 for r in engine.generate(PROMPTS, greedy))


def test_offload_reload_round_trip(engine):
    greedy = SamplingParams(max_new_tokens=6, greedy=True)
    before = engine.generate(PROMPTS, greedy)
    engine.offload()
    engine.offload()  # idempotent
    assert engine.is_offloaded
    with pytest.raises(RuntimeError, match="reload"):
        engine.generate(PROMPTS, greedy)
    engine.reload()
    assert not engine.is_offloaded
    assert engine.generate(PROMPTS, greedy) == before


def test_bad_prompts_fail_with_clear_errors(engine):
    with pytest.raises(ValueError, match="prompt 1 is empty"):
        engine.generate([[1, 2], []], SamplingParams())
    with pytest.raises(ValueError, match="outside the model's vocabulary"):
        engine.generate([[1, 100_000]], SamplingParams())
    with pytest.raises(ValueError, match="max_position_embeddings"):
        engine.generate([[1, 2]], SamplingParams(max_new_tokens=5000))
    with pytest.raises(TypeError, match="token ids"):
        engine.generate([["hello"]], SamplingParams())
    assert engine.generate([], SamplingParams()) == []


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n": 0}, "n=0"),
        ({"temperature": -1.0}, "temperature"),
        ({"top_p": 0.0}, "top_p"),
        ({"top_k": -1}, "top_k"),
        ({"max_new_tokens": 0}, "max_new_tokens"),
        ({"stop_strings": [""]}, "empty string"),
    ],
)
def test_sampling_params_validate(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SamplingParams(**kwargs)


def test_temperature_zero_means_greedy_with_t1_logprobs():
    assert SamplingParams(temperature=0.0).is_greedy
    assert SamplingParams(temperature=0.0).logprob_temperature == 1.0
    assert SamplingParams(temperature=0.5).logprob_temperature == 0.5


def per_token_reference(model, result, temperature: float, pad_token_id: int) -> torch.Tensor:
    reference, _ = recompute_logprobs(model, [result], temperature, pad_token_id)
    return reference


def switch_mid_generation(device: str, switch_at: int) -> None:
    """Partial rollouts: new weights loaded between decode steps. Every token's log-prob is the
    slow full-forward log-prob under the weights that sampled it (old before the switch, new from
    it: the KV cache is rebuilt, not reused), and each token carries that version."""
    old_model, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
    new_model = tiny_causal_lm(tokenizer="byte", seed=1)[0].to(device)
    engine = HFGenerateEngine(tiny_causal_lm(tokenizer="byte", seed=0)[0].to(device), tokenizer, eos_token_ids=[])
    calls = []

    def refresh():
        calls.append(1)
        if len(calls) == 1 + switch_at:  # one call before the prefill, then one per decode step
            engine.load_weights(new_model.named_parameters(), version=7)
            return True
        return False

    engine.weight_refresh = refresh
    sampling = SamplingParams(n=2, max_new_tokens=9, temperature=0.8, seed=11)
    results = engine.generate(PROMPTS, sampling)
    for r in results:
        assert r.weight_version == 0
        assert r.response_versions == [0] * switch_at + [7] * (9 - switch_at)
        old = per_token_reference(old_model, r, 0.8, tokenizer.pad_token_id)
        new = per_token_reference(new_model.cpu(), r, 0.8, tokenizer.pad_token_id)
        new_model.to(device)
        returned = torch.tensor(r.response_logprobs)
        torch.testing.assert_close(returned[:switch_at], old[:switch_at], atol=1e-5, rtol=0)
        torch.testing.assert_close(returned[switch_at:], new[switch_at:], atol=1e-5, rtol=0)
    engine.weight_refresh = None
    assert all(r.response_versions is None and r.weight_version == 7 for r in engine.generate(PROMPTS, sampling))


@pytest.mark.parametrize("switch_at", [1, 5])
def test_a_weight_update_mid_generation_switches_every_unfinished_row(switch_at):
    switch_mid_generation("cpu", switch_at)


def test_rows_finished_before_the_switch_keep_one_version(tiny):
    model, tokenizer = tiny
    engine = HFGenerateEngine(tiny_causal_lm(tokenizer="byte", seed=0)[0], tokenizer, eos_token_ids=[])
    first = engine.generate(PROMPTS, SamplingParams(max_new_tokens=6, greedy=True))
    stop = first[1].response_ids[1]  # the second prompt stops after two tokens
    steps = []

    def refresh():
        steps.append(1)
        if len(steps) == 5:
            engine.load_weights(tiny_causal_lm(tokenizer="byte", seed=1)[0].named_parameters(), version=1)
            return True
        return False

    engine.weight_refresh = refresh
    results = engine.generate(PROMPTS, SamplingParams(max_new_tokens=6, greedy=True, stop_token_ids=(stop,)))
    short = [r for r in results if r.finish_reason == "stop" and len(r.response_ids) <= 4]
    assert short and all(r.response_versions is None and r.weight_version == 0 for r in short)
    assert any(r.response_versions is not None for r in results)
