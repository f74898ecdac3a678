"""FSDP2 engine on CUDA: NCCL, bf16 compute, offload/reload. Skipped without CUDA (conftest.py).

Run on a GPU machine: ``pytest -m gpu tests/gpu/test_fsdp_gpu.py``; the two-rank test needs 2 GPUs.
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

from infinirl.data.batch import RESPONSE_MASK, pack_sequences
from infinirl.engines.fsdp import FSDPTrainEngine, init_distributed
from infinirl.engines.train_base import LoraSettings, TrainEngineConfig

pytestmark = pytest.mark.gpu

VOCAB = 128


def tiny_llama() -> LlamaForCausalLM:
    config = LlamaConfig(
        vocab_size=VOCAB,
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        num_key_value_heads=2,
        max_position_embeddings=64,
    )
    return LlamaForCausalLM(config)


def make_batch(seed: int, size: int = 4):
    gen = torch.Generator().manual_seed(seed)
    prompts, responses = [], []
    for _ in range(size):
        p, r = torch.randint(2, 9, (2,), generator=gen).tolist()
        prompts.append(torch.randint(1, VOCAB, (p,), generator=gen).tolist())
        responses.append(torch.randint(1, VOCAB, (r,), generator=gen).tolist())
    return pack_sequences(prompts, responses, pad_token_id=0)


def global_token_loss(num_tokens: float):
    def loss_fn(micro_batch, logprobs, entropy):
        loss = -(logprobs * micro_batch[RESPONSE_MASK]).sum() / num_tokens
        return loss, {"pg_loss": loss.detach()}

    return loss_fn


def train(engine, seeds):
    for seed in seeds:
        batch = make_batch(seed)
        engine.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))


def gpu_config(**overrides) -> TrainEngineConfig:
    defaults = dict(lr=1e-2, eps=1e-3, micro_batch_size=2, grad_clip=0.5, device="cuda", seed=0)
    defaults.update(overrides)
    return TrainEngineConfig(**defaults)


def exported(engine) -> dict[str, torch.Tensor]:
    return {name: tensor.detach().cpu().clone() for name, tensor in engine.state_dict_for_sync()}


def assert_weights_close(actual, expected, atol):
    assert actual.keys() == expected.keys()
    for name in expected:
        torch.testing.assert_close(actual[name], expected[name], atol=atol, rtol=0, msg=name)


@pytest.fixture(scope="module")
def one_gpu_group():
    if dist.is_initialized():  # e.g. a CPU (gloo-only) group left by another module
        pytest.skip("a process group already exists in this process")
    created = init_distributed("cuda")
    yield
    if created:
        dist.destroy_process_group()


@pytest.mark.parametrize("score_prompts", [True, False])
def test_bf16_logprobs_track_a_float64_reference(one_gpu_group, score_prompts):
    """bf16 log-probs on CUDA stay within 0.05 of a float64 CPU reference wherever they are read:
    every token with ``score_prompts``, else the response tokens (prompt columns are 0 then)."""
    engine = FSDPTrainEngine(tiny_llama, gpu_config(temperature=0.9, score_prompts=score_prompts))
    if torch.cuda.is_bf16_supported():
        assert engine.compute_dtype == torch.bfloat16
    batch = make_batch(1, size=5)
    logprobs, entropy = engine.compute_logprobs(batch, with_entropy=True)
    assert logprobs.is_cuda and logprobs.dtype == torch.float32

    reference = tiny_llama()
    reference.load_state_dict(exported(engine))
    reference = reference.double().eval()
    with torch.no_grad():
        logits = reference(
            input_ids=batch["input_ids"], attention_mask=batch["attention_mask"]
        ).logits
    log_p = torch.log_softmax(logits[:, :-1] / 0.9, dim=-1)
    ref = log_p.gather(-1, batch["input_ids"][:, 1:, None]).squeeze(-1)
    read = (batch["attention_mask"] if score_prompts else batch[RESPONSE_MASK])[:, 1:].bool()
    got = logprobs[:, 1:].cpu().double()
    torch.testing.assert_close(got[read], ref[read], atol=0.05, rtol=0)
    if not score_prompts:
        assert got[~read].abs().sum() == 0
    assert entropy.shape == logprobs.shape


def test_offload_frees_memory_and_training_continues_identically(one_gpu_group):
    straight = FSDPTrainEngine(tiny_llama, gpu_config())
    train(straight, [2, 3])

    engine = FSDPTrainEngine(tiny_llama, gpu_config())
    train(engine, [2])
    torch.cuda.synchronize()
    before = torch.cuda.memory_allocated()
    engine.offload()
    freed = before - torch.cuda.memory_allocated()
    params_bytes = sum(p.to_local().numel() * 4 for p in engine.model.parameters())
    assert freed >= 2 * params_bytes  # weights + two Adam moments
    assert all(p.to_local().device.type == "cpu" for p in engine.model.parameters())
    engine.reload()
    assert all(p.to_local().is_cuda for p in engine.model.parameters())
    train(engine, [3])
    assert_weights_close(exported(engine), exported(straight), atol=1e-6)


def test_checkpoint_resume_is_exact_on_gpu(one_gpu_group, tmp_path):
    cfg = gpu_config(warmup_steps=1, lr_schedule="cosine", total_steps=4)
    straight = FSDPTrainEngine(tiny_llama, cfg)
    train(straight, [4, 5, 6, 7])
    first = FSDPTrainEngine(tiny_llama, cfg)
    train(first, [4, 5])
    first.offload()  # saving from an offloaded engine works too
    first.save_checkpoint(tmp_path / "ckpt")
    resumed = FSDPTrainEngine(tiny_llama, replace(cfg, seed=99))
    resumed.load_checkpoint(tmp_path / "ckpt")
    train(resumed, [6, 7])
    assert_weights_close(exported(resumed), exported(straight), atol=1e-6)


def test_lora_on_gpu_trains_and_exports_merged(one_gpu_group):
    engine = FSDPTrainEngine(tiny_llama, gpu_config(lora=LoraSettings(r=4, alpha=8)))
    batch = make_batch(8)
    loss_fn = global_token_loss(batch[RESPONSE_MASK].sum().item())
    losses = [engine.train_step(batch, loss_fn)["train/loss"] for _ in range(5)]
    assert losses[-1] < losses[0]
    assert exported(engine).keys() == tiny_llama().state_dict().keys()


# ----------------------------------------------------------------------------- two GPUs


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def two_gpu_worker(rank: int, port: int, out_dir: str) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2"
    )
    os.environ["LOCAL_RANK"] = str(rank)
    init_distributed("cuda")
    try:
        engine = FSDPTrainEngine(tiny_llama, gpu_config())
        metrics = []
        for seed in (20, 21):
            batch = make_batch(seed)
            loss_fn = global_token_loss(batch[RESPONSE_MASK].sum().item())
            metrics.append(engine.train_step(batch[:2] if rank == 0 else batch[2:], loss_fn))
        weights = exported(engine)
        if rank == 0:
            torch.save({"metrics": metrics, "weights": weights}, os.path.join(out_dir, "rank0.pt"))
    finally:
        dist.destroy_process_group()


@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="needs two GPUs")
def test_two_gpus_match_one_gpu_nccl_bf16(tmp_path):
    mp.spawn(two_gpu_worker, args=(free_port(), str(tmp_path)), nprocs=2, join=True)
    two = torch.load(tmp_path / "rank0.pt", weights_only=False)
    # The one-rank reference runs in a fresh process too, so this test needs no group of its own.
    mp.spawn(one_gpu_reference, args=(free_port(), str(tmp_path)), nprocs=1, join=True)
    one = torch.load(tmp_path / "one.pt", weights_only=False)
    for two_metrics, one_metrics in zip(two["metrics"], one["metrics"]):
        assert two_metrics["train/grad_norm"] == pytest.approx(
            one_metrics["train/grad_norm"], rel=1e-4
        )
    # bf16 compute, fp32 sums; CUDA embedding backward accumulates with atomics (order varies).
    assert_weights_close(two["weights"], one["weights"], atol=2e-5)


def one_gpu_reference(rank: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK="0", WORLD_SIZE="1")
    init_distributed("cuda")
    try:
        engine = FSDPTrainEngine(tiny_llama, gpu_config())
        metrics = []
        for seed in (20, 21):
            batch = make_batch(seed)
            metrics.append(
                engine.train_step(batch, global_token_loss(batch[RESPONSE_MASK].sum().item()))
            )
        torch.save(
            {"metrics": metrics, "weights": exported(engine)}, os.path.join(out_dir, "one.pt")
        )
    finally:
        dist.destroy_process_group()
