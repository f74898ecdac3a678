"""VLLMEngine against transformers references, on tiny random Llamas saved to disk.

Slow suite, and only where vLLM is installed (its own venv: ``bash scripts/setup_vllm_venv.sh``):

    ~/.cache/infinirl/vllm-venv/bin/python -m pytest -m slow tests/integration/test_vllm_engine.py

One in-process engine serves the direct tests (vLLM's teardown resets process-wide state, so a
second one per process is avoided): tests that load other weights put the original ones back. The
last test runs the engine the way the runner does, inside a Ray rollout actor of its own.
"""

import pytest
import torch

from infinirl.engines.base import SamplingParams
from infinirl.engines.vllm_engine import vllm_available

pytestmark = pytest.mark.slow

if not vllm_available():
    pytest.skip(
        "vLLM is not installed in this environment (optional extra with its own pins: "
        "bash scripts/setup_vllm_venv.sh, then run pytest with that venv's python)",
        allow_module_level=True,
    )

from infinirl.components.rollout import RolloutWorker  # noqa: E402
from infinirl.engines.hf_generate import HFGenerateEngine  # noqa: E402
from infinirl.engines.registry import build_rollout_engine  # noqa: E402
from infinirl.engines.vllm_engine import VLLMEngine  # noqa: E402
from infinirl.models.hf_causal_lm import tiny_causal_lm  # noqa: E402
from infinirl.runtime import WeightSource, Worker, WorkerGroup, sync_weights  # noqa: E402
from tests.conftest import ship_by_value  # noqa: E402

ship_by_value(__name__)

PROMPTS = [[5, 6, 7, 8, 9, 10, 11], [20, 21], [30, 31, 32, 33]]
GREEDY = SamplingParams(max_new_tokens=10, greedy=True)


def _tiny(seed: int):
    # head_dim 32: vLLM's CPU attention supports head sizes 32, 64, 80, ... (not 16).
    return tiny_causal_lm(tokenizer="byte", seed=seed, hidden=64, heads=2, kv_heads=1)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Two tiny models with different weights, each also saved as an HF folder."""
    out = {}
    for name, seed in (("a", 0), ("b", 1)):
        model, tokenizer = _tiny(seed)
        folder = tmp_path_factory.mktemp(f"tiny_{name}")
        model.save_pretrained(folder)
        tokenizer.save_pretrained(folder)
        out[name] = (model, tokenizer, folder)
    return out


@pytest.fixture(scope="module")
def engine(models):
    """Built the way the rollout worker builds it: by registry name, options from the config.
    The tiny random model rarely emits EOS; tests pass stop ids explicitly where they need them."""
    options = {"kv_cache_bytes": 32 << 20, "max_model_len": 256, "eos_token_ids": []}
    eng = build_rollout_engine("vllm", str(models["a"][2]), "float32", "cpu", 64, options)
    assert isinstance(eng, VLLMEngine)
    yield eng
    eng.close()


def weights_of(model):
    """A generator, like the streamed buckets of a weight sync."""
    return ((name, tensor.detach().clone()) for name, tensor in model.state_dict().items())


def recompute(model, results, temperature: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Slow reference: one forward per sample, log_softmax(logits / T) at each response id."""
    reference, returned = [], []
    with torch.no_grad():
        for r in results:
            ids = torch.tensor([r.prompt_ids + r.response_ids])
            logprobs = torch.log_softmax(model(input_ids=ids).logits[0].float() / temperature, -1)
            start = len(r.prompt_ids) - 1
            positions = torch.arange(start, start + len(r.response_ids))
            reference.append(logprobs[positions, torch.tensor(r.response_ids)])
            returned.append(torch.tensor(r.response_logprobs))
    return torch.cat(reference), torch.cat(returned)


@pytest.mark.parametrize(
    "sampling",
    [
        SamplingParams(n=2, max_new_tokens=12, temperature=1.0, seed=3),
        SamplingParams(n=2, max_new_tokens=12, temperature=0.7, top_k=20, top_p=0.9, seed=4),
        SamplingParams(max_new_tokens=12, greedy=True),
    ],
    ids=["T=1", "T=0.7+topk+topp", "greedy"],
)
def test_logprobs_follow_our_convention(models, engine, sampling):
    """log softmax(logits / T) at the sampled id, no top-k/top-p renormalisation, T=1 greedy."""
    results = engine.generate(PROMPTS, sampling)
    assert all(len(r.response_logprobs) == len(r.response_ids) == 12 for r in results)
    reference, returned = recompute(models["a"][0], results, sampling.logprob_temperature)
    torch.testing.assert_close(returned, reference, atol=1e-4, rtol=0)


def test_truncated_sampling_reports_untruncated_logprobs(models, engine):
    """top_k=1 at T=0.7 samples the argmax; renormalised over the one survivor (vLLM's processed
    log-probs) every log-prob would be 0, ours are the full-vocabulary ones."""
    sampling = SamplingParams(n=2, max_new_tokens=8, temperature=0.7, top_k=1, seed=9)
    results = engine.generate(PROMPTS, sampling)
    reference, returned = recompute(models["a"][0], results, 0.7)
    torch.testing.assert_close(returned, reference, atol=1e-4, rtol=0)
    assert returned.max() < -1e-3


def test_greedy_matches_the_transformers_engine(models, engine):
    model, tokenizer, _ = models["a"]
    hf = HFGenerateEngine(model, tokenizer, eos_token_ids=[])
    ours = engine.generate(PROMPTS, GREEDY)
    assert [r.response_ids for r in ours] == [r.response_ids for r in hf.generate(PROMPTS, GREEDY)]
    assert engine.generate(PROMPTS, GREEDY) == ours  # deterministic


def test_results_are_prompt_major_with_version_and_finish_reason(engine):
    results = engine.generate(PROMPTS, SamplingParams(n=3, max_new_tokens=5, seed=1))
    assert [(r.prompt_index, r.sample_index) for r in results] == [
        (p, s) for p in range(len(PROMPTS)) for s in range(3)
    ]
    assert all(r.prompt_ids == PROMPTS[r.prompt_index] for r in results)
    assert all(r.finish_reason == "length" and len(r.response_ids) == 5 for r in results)
    assert all(r.weight_version == engine.weight_version for r in results)
    # Greedy with n > 1 (vLLM itself refuses it) gives n identical samples.
    greedy = engine.generate(PROMPTS[:1], SamplingParams(n=3, max_new_tokens=5, greedy=True))
    assert len({tuple(r.response_ids) for r in greedy}) == 1 and len(greedy) == 3


def test_seeds_reproduce_and_separate_samples(engine):
    def sample(seed, prompts=PROMPTS):
        return [r.response_ids for r in engine.generate(prompts, SamplingParams(n=3, max_new_tokens=8, seed=seed))]

    assert sample(7) == sample(7)
    assert sample(7) != sample(8)
    group = sample(7)[:3]
    assert len({tuple(s) for s in group}) == 3  # the samples of one prompt differ
    twice = sample(7, [PROMPTS[0], PROMPTS[0]])
    assert twice[:3] != twice[3:]  # the same prompt twice in a batch is not sampled identically
    torch.manual_seed(0)
    unseeded = [r.response_ids for r in engine.generate(PROMPTS, SamplingParams(n=2, max_new_tokens=8))]
    torch.manual_seed(0)
    assert unseeded == [r.response_ids for r in engine.generate(PROMPTS, SamplingParams(n=2, max_new_tokens=8))]


def test_stop_token_ids_and_eos_are_kept_and_end_the_response(engine):
    free = engine.generate(PROMPTS[:1], GREEDY)[0].response_ids
    stop = free[3]
    cut = free.index(stop) + 1
    result = engine.generate(PROMPTS[:1], SamplingParams(max_new_tokens=10, greedy=True, stop_token_ids=[stop]))[0]
    assert result.response_ids == free[:cut] and result.finish_reason == "stop"
    assert len(result.response_logprobs) == cut
    engine.eos_token_ids = (stop,)
    try:
        assert engine.generate(PROMPTS[:1], GREEDY)[0].response_ids == free[:cut]
        ignored = engine.generate(PROMPTS[:1], SamplingParams(max_new_tokens=10, greedy=True, ignore_eos=True))[0]
        assert ignored.response_ids == free and ignored.finish_reason == "length"
    finally:
        engine.eos_token_ids = ()


def test_stop_strings_match_the_transformers_engine(models, engine):
    model, tokenizer, _ = models["a"]
    hf = HFGenerateEngine(model, tokenizer, eos_token_ids=[])
    free = engine.generate(PROMPTS, SamplingParams(max_new_tokens=16, greedy=True))
    # A one-character ASCII stop string that prompt 0's greedy response produces (the tiny model
    # emits random bytes; ASCII keeps partial UTF-8 sequences out of the comparison).
    position, stop = next(
        (k, text) for k, token in enumerate(free[0].response_ids[1:], start=1)
        if len(text := tokenizer.decode([token])) == 1 and text.isascii() and text.isprintable()
    )
    sampling = SamplingParams(max_new_tokens=16, greedy=True, stop_strings=(stop,))
    ours, theirs = engine.generate(PROMPTS, sampling), hf.generate(PROMPTS, sampling)
    assert [r.response_ids for r in ours] == [r.response_ids for r in theirs]
    assert [r.finish_reason for r in ours] == [r.finish_reason for r in theirs]
    assert [r.extra for r in ours] == [r.extra for r in theirs]
    assert ours[0].finish_reason == "stop" and ours[0].extra == {"stop_string": stop}
    assert len(ours[0].response_ids) <= position + 1


def test_load_weights_from_a_generator_switches_the_model(models, engine):
    model_a, model_b = models["a"][0], models["b"][0]
    before = engine.generate(PROMPTS, GREEDY)  # also fills the prefix cache with A's KV blocks
    version = engine.weight_version
    try:
        engine.load_weights(weights_of(model_b), version=version + 7)
        assert engine.weight_version == version + 7
        sampling = SamplingParams(n=2, max_new_tokens=10, temperature=0.8, top_p=0.95, seed=2)
        results = engine.generate(PROMPTS, sampling)
        assert all(r.weight_version == version + 7 for r in results)
        reference, returned = recompute(model_b, results, 0.8)
        torch.testing.assert_close(returned, reference, atol=1e-4, rtol=0)
        hf_b = HFGenerateEngine(model_b, models["b"][1], eos_token_ids=[])
        after = engine.generate(PROMPTS, GREEDY)
        assert [r.response_ids for r in after] == [r.response_ids for r in hf_b.generate(PROMPTS, GREEDY)]
        assert [r.response_ids for r in after] != [r.response_ids for r in before]
    finally:
        engine.load_weights(weights_of(model_a), version=version + 8)
    assert [r.response_ids for r in engine.generate(PROMPTS, GREEDY)] == [r.response_ids for r in before]


def test_load_weights_rejects_partial_and_unknown_weights(models, engine):
    model_a, model_b = models["a"][0], models["b"][0]
    before = engine.generate(PROMPTS, GREEDY)
    version = engine.weight_version
    partial = [(n, t) for n, t in weights_of(model_a) if n != "model.norm.weight"]
    with pytest.raises(ValueError, match="not sent.*model.norm.weight"):
        engine.load_weights(iter(partial), version=version + 1)
    assert engine.weight_version == version
    with pytest.raises(ValueError, match="unknown weight name 'module.bogus.weight'"):
        engine.load_weights(iter([*weights_of(model_a), ("module.bogus.weight", torch.zeros(2))]), version + 1)
    wrong_shape = [(n, t[:1] if n == "model.norm.weight" else t) for n, t in weights_of(model_b)]
    with pytest.raises(ValueError, match="model.norm.weight.*shape"):
        engine.load_weights(iter(wrong_shape), version=version + 1)
    assert engine.weight_version == version
    engine.load_weights(weights_of(model_a), version=version)  # the engine still works
    assert engine.generate(PROMPTS, GREEDY) == before


def test_offload_frees_the_kv_cache_and_reload_restores_identical_generation(engine):
    before = engine.generate(PROMPTS, GREEDY)
    cache_bytes = engine.kv_cache_bytes()
    assert cache_bytes > 0
    engine.offload()
    engine.offload()  # idempotent
    assert engine.is_offloaded and engine.kv_cache_bytes() == 0
    with pytest.raises(RuntimeError, match="offloaded"):
        engine.generate(PROMPTS, GREEDY)
    engine.reload()
    engine.reload()  # idempotent
    assert not engine.is_offloaded and engine.kv_cache_bytes() == cache_bytes
    assert engine.generate(PROMPTS, GREEDY) == before


def test_weights_load_while_offloaded(models, engine):
    before = engine.generate(PROMPTS, GREEDY)
    engine.offload()
    try:
        engine.load_weights(weights_of(models["a"][0]), version=engine.weight_version + 1)
    finally:
        engine.reload()
    assert [r.response_ids for r in engine.generate(PROMPTS, GREEDY)] == [r.response_ids for r in before]


def test_prompt_validation(engine):
    with pytest.raises(ValueError, match="empty"):
        engine.generate([[]], GREEDY)
    with pytest.raises(ValueError, match="outside the model's vocabulary"):
        engine.generate([[5, 10_000]], GREEDY)
    with pytest.raises(ValueError, match="max_model_len=256"):
        engine.generate([[5] * 250], GREEDY)
    with pytest.raises(TypeError, match="token ids"):
        engine.generate([["hello"]], GREEDY)
    assert engine.generate([], GREEDY) == []


def test_sleep_level_2_is_refused_on_cpu(models, engine):
    with pytest.raises(ValueError, match="sleep_level=2 is not available on CPU"):
        VLLMEngine(models["a"][2], sleep_level=2)


class TinyTrainer(Worker, WeightSource):
    """Stands in for the actor: serves a tiny model's weights to ``sync_weights``."""

    def __init__(self, seed: int):
        self.model, _ = _tiny(seed)

    def weights_for_sync(self):
        return self.model.state_dict().items()


def test_rollout_worker_runs_vllm_in_a_ray_actor_and_takes_synced_weights(ray_cluster, models):
    """The runner's path: a Ray rollout rank with rollout.num_threads=2 (its methods run on an
    executor thread whose OpenMP count starts at Ray's OMP_NUM_THREADS=1), weights streamed in
    buckets through the object store into vLLM."""
    options = {"kv_cache_bytes": 32 << 20, "max_model_len": 256, "eos_token_ids": []}
    rollout = WorkerGroup.launch(RolloutWorker, "rollout", num_ranks=1,
                                 args=(str(models["a"][2]), "float32", 8, 2, "vllm", options))
    trainer = WorkerGroup.launch(TinyTrainer, "actor", num_ranks=1, args=(1,))
    try:
        for name, version in (("a", 0), ("b", 3)):
            model, tokenizer, _ = models[name]
            hf = HFGenerateEngine(model, tokenizer, eos_token_ids=[])
            results = rollout.generate(PROMPTS, GREEDY).wait()[0]
            assert [r.response_ids for r in results] == [r.response_ids for r in hf.generate(PROMPTS, GREEDY)]
            assert all(r.weight_version == version for r in results)
            if name == "a":
                stats = sync_weights(trainer, rollout, version=3, bucket_bytes=64 * 1024)
                assert stats.buckets >= 2
    finally:
        trainer.shutdown()
        rollout.shutdown()
