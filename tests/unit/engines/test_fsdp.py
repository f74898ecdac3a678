"""FSDP2 training engine on CPU (gloo): exactness against unsharded references.

Models are tiny random ``LlamaForCausalLM`` s (no hub). The loss everywhere is the contract the
PPO losses follow: a token sum divided by a *global* normaliser (all response tokens of the whole
mini-batch), so one rank with the whole batch and two ranks with half each must agree.
"""

from __future__ import annotations

import os
import socket
from dataclasses import replace

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from transformers import LlamaConfig, LlamaForCausalLM

from infinirl.algorithms.masking import masked_max, masked_min
from infinirl.data.batch import RESPONSE_MASK, pack_sequences
from infinirl.engines import distributed as distributed_module
from infinirl.engines import fsdp as fsdp_module
from infinirl.engines import fsdp_checkpoint
from infinirl.engines.fsdp import FSDPTrainEngine, init_distributed
from infinirl.engines.train_base import LoraSettings, LrSchedule, TrainEngineConfig

VOCAB = 64


def tiny_llama(tie: bool = False) -> LlamaForCausalLM:
    config = LlamaConfig(
        vocab_size=VOCAB,
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=4,
        num_key_value_heads=2,
        max_position_embeddings=64,
        tie_word_embeddings=tie,
    )
    return LlamaForCausalLM(config)


def make_batch(seed: int, size: int = 4):
    """Ragged prompts and responses, right-padded (the rollout's layout)."""
    gen = torch.Generator().manual_seed(seed)
    prompts, responses = [], []
    for _ in range(size):
        p, r = torch.randint(1, 6, (2,), generator=gen).tolist()
        prompts.append(torch.randint(1, VOCAB, (p,), generator=gen).tolist())
        responses.append(torch.randint(1, VOCAB, (r,), generator=gen).tolist())
    return pack_sequences(prompts, responses, pad_token_id=0)


def global_token_loss(num_tokens: float):
    """``-sum(logprobs * mask) / num_tokens``, ``num_tokens`` counted over the whole mini-batch;
    its metrics include the micro-batch's extreme log-probs (``_max`` / ``_min`` keys)."""

    def loss_fn(micro_batch, logprobs, entropy):
        mask = micro_batch[RESPONSE_MASK]
        loss = -(logprobs * mask).sum() / num_tokens
        return loss, {"pg_loss": loss.detach(), "tokens": mask.sum(),
                      "logprob_max": masked_max(logprobs.detach(), mask),
                      "logprob_min": masked_min(logprobs.detach(), mask)}

    return loss_fn


def config(**overrides) -> TrainEngineConfig:
    # device="cpu": these are the CPU tests even on a GPU machine. eps=1e-3 keeps Adam's first
    # step (~lr * g / |g|) from amplifying float round-off in near-zero gradients.
    defaults = dict(lr=1e-2, eps=1e-3, micro_batch_size=2, grad_clip=None, seed=0, device="cpu")
    defaults.update(overrides)
    return TrainEngineConfig(**defaults)


def exported(engine: FSDPTrainEngine) -> dict[str, torch.Tensor]:
    return {name: tensor.clone() for name, tensor in engine.state_dict_for_sync()}


def assert_weights_close(actual: dict, expected: dict, atol: float) -> None:
    assert actual.keys() == expected.keys()
    for name in expected:
        torch.testing.assert_close(actual[name], expected[name], atol=atol, rtol=0, msg=name)


def reference_model(weights: dict[str, torch.Tensor], tie: bool = False) -> LlamaForCausalLM:
    model = tiny_llama(tie)
    model.load_state_dict(weights)
    return model.double().eval()


def reference_logprobs(model, batch, temperature: float):
    """Unpadded, one sequence at a time, float64 log-softmax, token loop."""
    lengths = batch["attention_mask"].sum(1)
    logprobs = torch.zeros(batch["input_ids"].shape, dtype=torch.float64)
    entropy = torch.zeros_like(logprobs)
    with torch.no_grad():
        for b, n in enumerate(lengths.tolist()):
            ids = batch["input_ids"][b, :n]
            logits = model(input_ids=ids[None]).logits[0]
            for t in range(1, n):
                log_p = torch.log_softmax(logits[t - 1] / temperature, dim=-1)
                logprobs[b, t] = log_p[ids[t]]
                entropy[b, t] = -(log_p.exp() * log_p).sum()
    return logprobs, entropy


@pytest.fixture(scope="module", autouse=True)
def one_rank_group():
    """A one-rank gloo group for the in-process engines; destroyed when the module is done."""
    torch.set_num_threads(1)  # 2 shared cores: threads only contend on tiny matmuls
    created = init_distributed()
    yield
    if created:
        dist.destroy_process_group()


# ----------------------------------------------------------------------------- log-probs


@pytest.mark.parametrize("tie", [False, True])
def test_compute_logprobs_matches_unpadded_float64_reference(tie):
    engine = FSDPTrainEngine(lambda: tiny_llama(tie), config(micro_batch_size=3, temperature=0.8, score_prompts=True))
    batch = make_batch(seed=1, size=5)
    logprobs, entropy = engine.compute_logprobs(batch, with_entropy=True)
    ref_lp, ref_ent = reference_logprobs(reference_model(exported(engine), tie), batch, 0.8)
    assert logprobs.shape == entropy.shape == batch["input_ids"].shape
    torch.testing.assert_close(logprobs.double(), ref_lp, atol=1e-5, rtol=0)
    torch.testing.assert_close(entropy.double(), ref_ent, atol=1e-5, rtol=0)


def long_prompt_batch(seed: int, size: int = 4):
    """Prompts of 6..9 tokens and responses of 1..4: the earliest response starts at column 6."""
    gen = torch.Generator().manual_seed(seed)
    prompts = [torch.randint(1, VOCAB, (6 + i % 4,), generator=gen).tolist() for i in range(size)]
    responses = [torch.randint(1, VOCAB, (1 + i % 4,), generator=gen).tolist() for i in range(size)]
    return pack_sequences(prompts, responses, pad_token_id=0)


def test_responses_only_scoring_is_exact_where_it_is_read_and_skips_the_prompts(monkeypatch):
    """score_prompts=False without prompt packing: the LM head runs from column 5 on (one before
    the earliest response token); response log-probs/entropies equal the float64 reference,
    earlier columns are 0, and a training step moves the weights exactly as full scoring does."""
    seen = []
    original = fsdp_module.first_scored_column
    monkeypatch.setattr(fsdp_module, "first_scored_column", lambda *a: seen.append(original(*a)) or seen[-1])
    batch = long_prompt_batch(seed=3, size=4)
    engine = FSDPTrainEngine(tiny_llama, config(micro_batch_size=4, temperature=0.8, share_prompt_prefix=False))
    logprobs, entropy = engine.compute_logprobs(batch, with_entropy=True)
    assert seen == [5]
    ref_lp, ref_ent = reference_logprobs(reference_model(exported(engine)), batch, 0.8)
    mask = batch[RESPONSE_MASK].bool()
    torch.testing.assert_close(logprobs.double()[mask], ref_lp[mask], atol=1e-5, rtol=0)
    torch.testing.assert_close(entropy.double()[mask], ref_ent[mask], atol=1e-5, rtol=0)
    assert logprobs[:, :5].abs().sum() == 0 and ref_lp[:, 1:5].abs().sum() > 0

    tokens = float(batch[RESPONSE_MASK].sum())
    full = FSDPTrainEngine(tiny_llama, config(micro_batch_size=2, score_prompts=True))
    part = FSDPTrainEngine(tiny_llama, config(micro_batch_size=2, share_prompt_prefix=False))
    assert_weights_close(exported(part), exported(full), atol=0)
    full.train_step(batch, global_token_loss(tokens))
    part.train_step(batch, global_token_loss(tokens))
    assert_weights_close(exported(part), exported(full), atol=1e-6)


def test_exported_weights_are_the_models_with_hf_names():
    engine = FSDPTrainEngine(tiny_llama, config())
    torch.manual_seed(0)
    expected = tiny_llama().state_dict()  # the factory under the engine's seed
    assert_weights_close(exported(engine), dict(expected), atol=0)
    bf16 = dict(engine.state_dict_for_sync(dtype=torch.bfloat16))
    assert all(t.dtype == torch.bfloat16 for t in bf16.values())


def test_from_pretrained_loads_a_local_checkpoint(tmp_path):
    torch.manual_seed(42)
    tiny_llama().save_pretrained(tmp_path / "model")
    torch.manual_seed(42)
    expected = tiny_llama().state_dict()
    engine = FSDPTrainEngine.from_pretrained(str(tmp_path / "model"), config())
    assert_weights_close(exported(engine), dict(expected), atol=0)


def test_logprobs_after_a_step_see_the_new_weights():
    engine = FSDPTrainEngine(tiny_llama, config())
    batch = make_batch(seed=2)
    before, _ = engine.compute_logprobs(batch)
    engine.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))
    after, _ = engine.compute_logprobs(batch)
    ref, _ = reference_logprobs(reference_model(exported(engine)), batch, 1.0)
    mask = batch[RESPONSE_MASK].bool()  # what the engine scores by default (score_prompts=False)
    assert not torch.allclose(before[mask], after[mask])
    torch.testing.assert_close(after.double()[mask], ref[mask], atol=1e-5, rtol=0)


# ----------------------------------------------------------------------------- train step


def test_micro_batch_size_does_not_change_the_update():
    batch = make_batch(seed=3)
    loss_fn = global_token_loss(batch[RESPONSE_MASK].sum().item())
    results = []
    for micro_batch_size in (1, 4):
        engine = FSDPTrainEngine(tiny_llama, config(micro_batch_size=micro_batch_size))
        metrics = engine.train_step(batch, loss_fn)
        results.append((metrics, exported(engine)))
    (m1, w1), (m4, w4) = results
    assert_weights_close(w1, w4, atol=1e-6)
    assert m1["train/loss"] == pytest.approx(m4["train/loss"], abs=1e-6)
    assert m1["train/grad_norm"] == pytest.approx(m4["train/grad_norm"], rel=1e-5)
    # loss_fn metrics are means over micro-batches: 4 micro-batches of ~1/4 of the tokens each.
    assert m1["tokens"] == pytest.approx(batch[RESPONSE_MASK].sum().item() / 4)
    # ... but a _max / _min key is the extreme over the micro-batches: the whole batch's
    logprobs, _ = FSDPTrainEngine(tiny_llama, config()).compute_logprobs(batch)
    mask = batch[RESPONSE_MASK].bool()
    for metrics in (m1, m4):
        assert metrics["logprob_max"] == pytest.approx(float(logprobs[mask].max()), abs=1e-5)
        assert metrics["logprob_min"] == pytest.approx(float(logprobs[mask].min()), abs=1e-5)


def unsharded_grad_norm(batch, loss_fn) -> float:
    torch.manual_seed(0)
    model = tiny_llama()
    from infinirl.engines.logprobs import aligned_logprobs

    out = model(
        input_ids=batch["input_ids"],
        attention_mask=batch["attention_mask"],
        position_ids=batch["position_ids"],
    )
    logprobs, _ = aligned_logprobs(out.logits, batch["input_ids"], batch["attention_mask"])
    loss, _ = loss_fn(batch, logprobs, None)
    loss.backward()
    return torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in model.parameters()])).item()


def test_grad_norm_is_the_global_norm_and_clipping_applies_it():
    batch = make_batch(seed=4)
    loss_fn = global_token_loss(batch[RESPONSE_MASK].sum().item())
    expected = unsharded_grad_norm(batch, loss_fn)

    engine = FSDPTrainEngine(tiny_llama, config(grad_clip=0.25))
    seen = []

    def record_norm_before_step(optimizer, args, kwargs):
        grads = [p.grad.full_tensor() for p in engine.model.parameters() if p.grad is not None]
        seen.append(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads])).item())

    engine.optimizer.register_step_pre_hook(record_norm_before_step)
    metrics = engine.train_step(batch, loss_fn)
    assert expected > 0.25  # otherwise this test proves nothing about clipping
    assert metrics["train/grad_norm"] == pytest.approx(expected, rel=1e-5)
    assert seen == [pytest.approx(0.25, rel=1e-5)]


def test_non_finite_gradient_skips_the_update():
    engine = FSDPTrainEngine(tiny_llama, config())
    before = exported(engine)

    def nan_loss(micro_batch, logprobs, entropy):
        return logprobs.sum() * float("nan"), {}

    metrics = engine.train_step(make_batch(seed=5), nan_loss)
    assert metrics["train/skipped_step"] == 1.0
    assert_weights_close(exported(engine), before, atol=0)


def test_loss_fn_errors_are_clear():
    engine = FSDPTrainEngine(tiny_llama, config())
    batch = make_batch(seed=6)
    with pytest.raises(TypeError, match="scalar"):
        engine.train_step(batch, lambda mb, lp, ent: (lp, {}))
    with pytest.raises(ValueError, match="does not depend"):
        engine.train_step(batch, lambda mb, lp, ent: (lp.detach().sum(), {}))
    # A failed step leaves the engine usable.
    metrics = engine.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))
    assert metrics["train/skipped_step"] == 0.0


def test_activation_checkpointing_gives_the_same_update():
    batch = make_batch(seed=7)
    loss_fn = global_token_loss(batch[RESPONSE_MASK].sum().item())
    weights = []
    for checkpointing in (False, True):
        engine = FSDPTrainEngine(tiny_llama, config(activation_checkpointing=checkpointing))
        engine.train_step(batch, loss_fn, with_entropy=True)
        weights.append(exported(engine))
    assert_weights_close(weights[0], weights[1], atol=1e-6)


def test_lr_schedule_warmup_then_cosine():
    schedule = LrSchedule(
        config(warmup_steps=2, lr_schedule="cosine", total_steps=6, min_lr_ratio=0.1)
    )
    factors = [schedule(step) for step in range(7)]
    assert factors[:3] == [0.5, 1.0, 1.0]
    assert factors[4] == pytest.approx(0.1 + 0.9 * 0.5)
    assert factors[6] == pytest.approx(0.1)
    assert LrSchedule(config())(100) == 1.0


def test_config_rejects_nonsense():
    with pytest.raises(ValueError, match="total_steps"):
        TrainEngineConfig(lr_schedule="cosine")
    with pytest.raises(ValueError, match="micro_batch_size"):
        TrainEngineConfig(micro_batch_size=0)
    assert TrainEngineConfig(lora={"r": 2}).lora == LoraSettings(r=2)


def test_bf16_compute_on_cpu_stays_close_to_fp32(monkeypatch):
    monkeypatch.setattr(distributed_module, "resolve_cpu_dtype", lambda name: name)  # bf16 even without native bf16
    batch = make_batch(seed=8)
    fp32, _ = FSDPTrainEngine(tiny_llama, config(param_dtype="float32")).compute_logprobs(batch)
    engine = FSDPTrainEngine(tiny_llama, config(param_dtype="bfloat16"))
    bf16, _ = engine.compute_logprobs(batch)
    assert engine.compute_dtype == torch.bfloat16 and bf16.dtype == torch.float32
    torch.testing.assert_close(bf16, fp32, atol=0.1, rtol=0)
    metrics = engine.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))
    assert metrics["train/skipped_step"] == 0.0


# ----------------------------------------------------------------------------- LoRA


def test_lora_trains_only_adapters_and_exports_merged_weights():
    lora = LoraSettings(r=4, alpha=8, target_modules=["q_proj", "v_proj", "down_proj"])
    engine = FSDPTrainEngine(tiny_llama, config(lora=lora, lr=2e-2))
    batch = make_batch(seed=9)
    loss_fn = global_token_loss(batch[RESPONSE_MASK].sum().item())

    def full_state():
        return {k: v.full_tensor().clone() for k, v in engine.model.state_dict().items()}

    start = full_state()
    losses = [engine.train_step(batch, loss_fn)["train/loss"] for _ in range(5)]
    end = full_state()
    assert losses[-1] < losses[0] - 0.05, losses
    for name in start:
        changed = not torch.equal(start[name], end[name])
        assert changed == (".lora_B." in name or ".lora_A." in name), name

    merged = exported(engine)
    torch.manual_seed(0)
    assert merged.keys() == tiny_llama().state_dict().keys()
    q_base = end["base_model.model.model.layers.0.self_attn.q_proj.base_layer.weight"]
    q_a = end["base_model.model.model.layers.0.self_attn.q_proj.lora_A.default.weight"]
    q_b = end["base_model.model.model.layers.0.self_attn.q_proj.lora_B.default.weight"]
    torch.testing.assert_close(
        merged["model.layers.0.self_attn.q_proj.weight"], q_base + (8 / 4) * q_b @ q_a
    )
    # The merged plain model scores tokens exactly like the adapted engine.
    logprobs, _ = engine.compute_logprobs(batch)
    ref, _ = reference_logprobs(reference_model(merged), batch, 1.0)
    mask = batch[RESPONSE_MASK].bool()  # what the engine scores (prompt columns read 0)
    torch.testing.assert_close(logprobs.double()[mask], ref[mask], atol=1e-5, rtol=0)


# ----------------------------------------------------------------------------- checkpoints


def train_steps(engine, seeds):
    for seed in seeds:
        batch = make_batch(seed)
        engine.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))


def test_checkpoint_resume_continues_exactly(tmp_path):
    cfg = config(
        warmup_steps=2, lr_schedule="cosine", total_steps=4, weight_decay=0.1, grad_clip=1.0
    )
    straight = FSDPTrainEngine(tiny_llama, cfg)
    train_steps(straight, [10, 11, 12, 13])

    first = FSDPTrainEngine(tiny_llama, cfg)
    train_steps(first, [10, 11])
    first.save_checkpoint(tmp_path / "ckpt")
    rng_after_save = torch.rand(3)

    resumed = FSDPTrainEngine(tiny_llama, replace(cfg, seed=123))  # different init: all from disk
    resumed.load_checkpoint(tmp_path / "ckpt")
    assert torch.equal(torch.rand(3), rng_after_save)
    assert resumed.global_step == 2
    train_steps(resumed, [12, 13])

    assert_weights_close(exported(resumed), exported(straight), atol=1e-7)
    assert resumed.scheduler.get_last_lr() == straight.scheduler.get_last_lr()
    assert not list(tmp_path.glob("*.tmp"))


def test_checkpoint_before_any_step_keeps_optimizer_fresh(tmp_path):
    straight = FSDPTrainEngine(tiny_llama, config())
    fresh = FSDPTrainEngine(tiny_llama, config())
    fresh.save_checkpoint(tmp_path / "step0")  # must not initialise Adam's state (step count)
    train_steps(fresh, [14])
    train_steps(straight, [14])
    assert_weights_close(exported(fresh), exported(straight), atol=0)
    loaded = FSDPTrainEngine(tiny_llama, config(seed=5))
    loaded.load_checkpoint(tmp_path / "step0")
    train_steps(loaded, [14])
    assert_weights_close(exported(loaded), exported(straight), atol=1e-7)


def test_failed_save_leaves_no_partial_directory_and_keeps_the_old_one(tmp_path, monkeypatch):
    engine = FSDPTrainEngine(tiny_llama, config())
    train_steps(engine, [15])
    target = tmp_path / "ckpt"
    engine.save_checkpoint(target)
    saved = exported(engine)
    train_steps(engine, [16])

    def crash(state, file):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(fsdp_checkpoint, "write_engine_state", crash)
    with pytest.raises(OSError, match="simulated"):
        engine.save_checkpoint(target)
    with pytest.raises(OSError, match="simulated"):
        engine.save_checkpoint(tmp_path / "never")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt"]

    restored = FSDPTrainEngine(tiny_llama, config(seed=9))
    restored.load_checkpoint(target)
    assert_weights_close(exported(restored), saved, atol=0)


def test_load_checkpoint_rejects_a_foreign_directory(tmp_path):
    engine = FSDPTrainEngine(tiny_llama, config())
    with pytest.raises(FileNotFoundError, match="not an engine checkpoint"):
        engine.load_checkpoint(tmp_path)


# ----------------------------------------------------------------------------- offload


def test_offload_reload_on_cpu_is_a_working_no_op():
    engine = FSDPTrainEngine(tiny_llama, config())
    batch = make_batch(seed=17)
    engine.offload()
    assert engine.is_offloaded
    with pytest.raises(RuntimeError, match="reload"):
        engine.compute_logprobs(batch)
    engine.reload()
    assert not engine.is_offloaded
    metrics = engine.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))
    assert metrics["train/skipped_step"] == 0.0


# ----------------------------------------------------------------------------- two ranks


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def split_steps():
    """Two steps on global batches of 4 and 5: an even split, then 4 + 1 (rank 1 runs a filler)."""
    return [(make_batch(20, 4), 2), (make_batch(21, 5), 4)]


def two_rank_worker(rank: int, port: int, out_dir: str) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2"
    )
    torch.set_num_threads(1)
    init_distributed()
    try:
        engine = FSDPTrainEngine(tiny_llama, config(grad_clip=0.5))
        results = {"metrics": [], "logprobs": []}
        for batch, split in split_steps():
            mine = batch[:split] if rank == 0 else batch[split:]
            results["logprobs"].append(engine.compute_logprobs(mine)[0])
            loss_fn = global_token_loss(batch[RESPONSE_MASK].sum().item())
            results["metrics"].append(engine.train_step(mine, loss_fn))
        results["weights"] = exported(engine)  # every rank gathers; rank 0 reports
        engine.save_checkpoint(os.path.join(out_dir, "ckpt"))
        if rank == 0:
            torch.save(results, os.path.join(out_dir, "rank0.pt"))
    finally:
        dist.destroy_process_group()


def test_two_ranks_match_one_rank(tmp_path):
    mp.spawn(two_rank_worker, args=(free_port(), str(tmp_path)), nprocs=2, join=True)
    two = torch.load(tmp_path / "rank0.pt", weights_only=False)

    one = FSDPTrainEngine(tiny_llama, config(grad_clip=0.5))
    for step, (batch, split) in enumerate(split_steps()):
        logprobs, _ = one.compute_logprobs(batch)
        torch.testing.assert_close(two["logprobs"][step], logprobs[:split], atol=1e-6, rtol=0)
        metrics = one.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))
        assert two["metrics"][step]["train/grad_norm"] == pytest.approx(
            metrics["train/grad_norm"], rel=1e-5
        )
        assert two["metrics"][step]["train/loss"] == pytest.approx(metrics["train/loss"], abs=1e-6)
        # _max / _min: the extreme over both ranks' micro-batches, the whole mini-batch's
        mask = batch[RESPONSE_MASK].bool()
        assert two["metrics"][step]["logprob_max"] == pytest.approx(float(logprobs[mask].max()), abs=1e-5)
        assert two["metrics"][step]["logprob_min"] == pytest.approx(float(logprobs[mask].min()), abs=1e-5)
    assert metrics["train/grad_norm"] > 0.5  # clipping was active, with the global norm
    assert_weights_close(two["weights"], exported(one), atol=1e-6)

    # A checkpoint written by two ranks loads into one (DCP reshards).
    restored = FSDPTrainEngine(tiny_llama, config(seed=3))
    restored.load_checkpoint(tmp_path / "ckpt")
    assert_weights_close(exported(restored), two["weights"], atol=0)


# ----------------------------------------------------------------------------- dropout


def tiny_gpt2(head: str = "lm"):
    """GPT-2 keeps its default dropout (0.1 on embeddings, attention and residuals)."""
    from transformers import GPT2Config, GPT2ForTokenClassification, GPT2LMHeadModel

    cfg = GPT2Config(vocab_size=VOCAB, n_positions=64, n_embd=32, n_layer=2, n_head=4, num_labels=1,
                     bos_token_id=1, eos_token_id=1)
    assert cfg.resid_pdrop > 0 and cfg.attn_pdrop > 0
    return GPT2LMHeadModel(cfg) if head == "lm" else GPT2ForTokenClassification(cfg)


def tiny_opt():
    """OPT drops through functional dropout with rates kept on its modules, and skips whole layers."""
    from transformers import OPTConfig, OPTForCausalLM

    return OPTForCausalLM(OPTConfig(vocab_size=VOCAB, hidden_size=32, ffn_dim=64, num_hidden_layers=2,
                                    num_attention_heads=4, max_position_embeddings=64, word_embed_proj_dim=32,
                                    dropout=0.1, attention_dropout=0.1, layerdrop=0.5))


@pytest.mark.parametrize("factory, output", [(tiny_gpt2, "logprobs"), (lambda: tiny_gpt2("values"), "values"),
                                             (tiny_opt, "logprobs")], ids=["gpt2", "gpt2-critic", "opt"])
def test_dropout_is_off_so_train_mode_forwards_are_deterministic(factory, output):
    engine = FSDPTrainEngine(factory, config(micro_batch_size=4), output=output)
    rates = {k: v for k, v in engine.model.config.to_dict().items() if "drop" in k and isinstance(v, float)}
    assert rates and not any(rates.values()), rates
    batch = make_batch(seed=5)
    ids = batch["input_ids"]
    engine.model.train()
    with torch.no_grad():
        first, second = engine.model(input_ids=ids).logits, engine.model(input_ids=ids).logits
    assert torch.equal(first, second)
    # The update's forward (train mode) sees what the eval-mode scoring saw: the PPO ratio starts at 1.
    scored = engine.compute_values(batch) if output == "values" else engine.compute_logprobs(batch)[0]
    seen = []

    def loss_fn(micro, out, _entropy):
        seen.append(out.detach())
        return (out * micro[RESPONSE_MASK]).sum() * 0.0, {}

    engine.train_step(batch, loss_fn)
    mask = batch[RESPONSE_MASK].bool()
    torch.testing.assert_close(torch.cat(seen)[mask], scored[mask], atol=1e-6, rtol=0)
