"""The FSDP2 engine in its other PPO roles: critic (values), frozen reference, LoRA base as reference.

Same ground rules as ``test_fsdp.py``: tiny random Llamas on CPU (gloo, one rank), checked against
slow float64 references computed one unpadded sequence at a time.
"""

from __future__ import annotations

import pytest
import torch
import torch.distributed as dist
from transformers import LlamaConfig, LlamaForCausalLM, LlamaForTokenClassification

from infinirl.algorithms.masking import explained_variance
from infinirl.components.critic import CriticWorker
from infinirl.data.batch import RESPONSE_MASK, pack_sequences
from infinirl.engines.fsdp import FSDPTrainEngine, init_distributed
from infinirl.engines.logprobs import aligned_values
from infinirl.engines.train_base import LoraSettings, TrainEngineConfig
from infinirl.runtime import RankContext

VOCAB = 64


def llama_config(**extra) -> LlamaConfig:
    return LlamaConfig(vocab_size=VOCAB, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                       num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=64, **extra)


def tiny_policy() -> LlamaForCausalLM:
    return LlamaForCausalLM(llama_config())


def tiny_value_model() -> LlamaForTokenClassification:
    return LlamaForTokenClassification(llama_config(num_labels=1, classifier_dropout=0.0))


def make_batch(seed: int, size: int = 4):
    gen = torch.Generator().manual_seed(seed)
    prompts, responses = [], []
    for _ in range(size):
        p, r = torch.randint(1, 6, (2,), generator=gen).tolist()
        prompts.append(torch.randint(1, VOCAB, (p,), generator=gen).tolist())
        responses.append(torch.randint(1, VOCAB, (r,), generator=gen).tolist())
    return pack_sequences(prompts, responses, pad_token_id=0)


def config(**overrides) -> TrainEngineConfig:
    defaults = dict(lr=1e-2, eps=1e-3, micro_batch_size=2, grad_clip=None, seed=0, device="cpu")
    defaults.update(overrides)
    return TrainEngineConfig(**defaults)


def token_loss(batch):
    total = batch[RESPONSE_MASK].sum().item()

    def loss_fn(micro, logprobs, entropy):
        loss = -(logprobs * micro[RESPONSE_MASK]).sum() / total
        return loss, {}

    return loss_fn


@pytest.fixture(scope="module", autouse=True)
def one_rank_group():
    torch.set_num_threads(1)
    created = init_distributed()
    yield
    if created:
        dist.destroy_process_group()


# ----------------------------------------------------------------------------- critic


def reference_values(weights: dict, batch) -> torch.Tensor:
    """float64, one unpadded sequence at a time, value of token t read from position t - 1."""
    model = tiny_value_model()
    model.load_state_dict(weights)
    model = model.double().eval()
    out = torch.zeros(batch["input_ids"].shape, dtype=torch.float64)
    with torch.no_grad():
        for b, n in enumerate(batch["attention_mask"].sum(1).tolist()):
            per_position = model(input_ids=batch["input_ids"][b, :n][None]).logits[0, :, 0]
            for t in range(1, n):
                out[b, t] = per_position[t - 1]
    return out


def test_aligned_values_shift_and_mask():
    values = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    mask = torch.tensor([[1, 1, 1, 0]])
    assert aligned_values(values, mask).tolist() == [[0.0, 1.0, 2.0, 0.0]]


def test_value_engine_matches_unpadded_float64_reference():
    engine = FSDPTrainEngine(tiny_value_model, config(micro_batch_size=3), output="values")
    torch.manual_seed(0)
    weights = tiny_value_model().state_dict()  # the factory under the engine's seed
    batch = make_batch(seed=1, size=5)
    values = engine.compute_values(batch)
    assert values.shape == batch["input_ids"].shape and values.dtype == torch.float32
    torch.testing.assert_close(values.double(), reference_values(weights, batch), atol=1e-5, rtol=0)
    with pytest.raises(RuntimeError, match="outputs values, not logprobs"):
        engine.compute_logprobs(batch)


def test_critic_from_a_causal_lm_keeps_its_backbone_and_starts_at_zero(tmp_path):
    torch.manual_seed(3)
    policy = tiny_policy()
    policy.save_pretrained(tmp_path / "model")
    engine = FSDPTrainEngine.from_pretrained(str(tmp_path / "model"), config(), output="values")
    batch = make_batch(seed=2)
    assert torch.equal(engine.compute_values(batch), torch.zeros(batch["input_ids"].shape))
    exported = dict(engine.state_dict_for_sync())
    for name, tensor in policy.state_dict().items():
        if name.startswith("model."):
            torch.testing.assert_close(exported[name], tensor, atol=0, rtol=0, msg=name)


def in_process(worker_cls, *args):
    """A Worker built in this process (no Ray): the runtime would set ``ctx`` before ``__init__``."""
    worker = worker_cls.__new__(worker_cls)
    worker.ctx = RankContext(component=worker_cls.__name__, rank=0, world_size=1)
    worker.__init__(*args)
    return worker


@pytest.mark.parametrize("lora", [None, LoraSettings(r=4, alpha=8)], ids=["full", "lora"])
def test_critic_fits_returns_on_a_fixed_batch(tmp_path, lora):
    torch.manual_seed(4)
    tiny_policy().save_pretrained(tmp_path / "model")
    critic = in_process(CriticWorker, str(tmp_path / "model"), config(lr=1e-2, lora=lora), 10.0)
    batch = make_batch(seed=5, size=6)
    mask = batch[RESPONSE_MASK]
    # Learnable targets: a function of the state the value is read from (the token before t).
    previous = torch.roll(batch["input_ids"], shifts=1, dims=1)
    batch["returns"] = (previous % 2).float() * mask
    tokens = float(mask.sum())
    losses, variance_explained = [], []
    for _ in range(12):
        batch["values"] = critic.compute_values(batch)
        variance_explained.append(float(explained_variance(batch["values"], batch["returns"], mask)))
        metrics = critic.train_step(batch, tokens)
        losses.append(metrics["train/value_loss"])
    assert variance_explained[0] == 0.0  # a zero-initialised head explains nothing
    assert losses[-1] < 0.25 * losses[0], losses
    assert variance_explained[-1] > 0.6, variance_explained
    assert {"train/value_clip_fraction", "train/value_mse", "train/critic_grad_norm", "train/critic_lr"} <= set(metrics)


def test_value_clipping_bounds_the_move_from_the_old_values():
    from infinirl.components.critic import critic_loss

    batch = make_batch(seed=7)
    mask = batch[RESPONSE_MASK]
    batch["values"] = torch.zeros(mask.shape)
    batch["returns"] = torch.ones(mask.shape) * mask
    moved_far = torch.full(mask.shape, 5.0, requires_grad=True)  # overshoots: clipped side is worse
    loss, metrics = critic_loss(batch, moved_far, 0.5, float(mask.sum()))
    assert metrics["train/value_clip_fraction"] == pytest.approx(0.0)  # (5-1)^2 > (0.5-1)^2: unclipped is max
    close = torch.full(mask.shape, 0.9, requires_grad=True)  # beyond the clip, towards the target
    _, metrics = critic_loss(batch, close, 0.5, float(mask.sum()))
    assert metrics["train/value_clip_fraction"] == pytest.approx(1.0)


# ----------------------------------------------------------------------------- reference


def test_frozen_engine_scores_like_the_trainable_one_and_refuses_to_train():
    actor = FSDPTrainEngine(tiny_policy, config())
    reference = FSDPTrainEngine(tiny_policy, config(), trainable=False)
    assert reference.optimizer is None
    assert not any(p.requires_grad for p in reference.model.parameters())
    batch = make_batch(seed=8)
    assert torch.equal(actor.compute_logprobs(batch)[0], reference.compute_logprobs(batch)[0])
    with pytest.raises(RuntimeError, match="frozen"):
        reference.train_step(batch, token_loss(batch))
    with pytest.raises(ValueError, match="takes no LoRA"):
        FSDPTrainEngine(tiny_policy, config(lora=LoraSettings(r=2)), trainable=False)


def test_lora_base_with_the_adapter_off_is_the_initial_policy():
    engine = FSDPTrainEngine(tiny_policy, config(lora=LoraSettings(r=4, alpha=8)))
    batch = make_batch(seed=9)
    initial, _ = engine.compute_logprobs(batch)
    for _ in range(3):
        engine.train_step(batch, token_loss(batch))
    trained, _ = engine.compute_logprobs(batch)
    assert (trained - initial).abs().max() > 1e-3
    reference, _ = engine.compute_logprobs(batch, adapter=False)
    torch.testing.assert_close(reference, initial, atol=1e-6, rtol=0)
    # The adapter is back on, and still trains.
    assert torch.equal(engine.compute_logprobs(batch)[0], trained)
    engine.train_step(batch, token_loss(batch))
    assert not torch.equal(engine.compute_logprobs(batch)[0], trained)
    plain = FSDPTrainEngine(tiny_policy, config())
    with pytest.raises(ValueError, match="needs a LoRA engine"):
        plain.compute_logprobs(batch, adapter=False)


def test_critic_checkpoint_resume_continues_exactly(tmp_path):
    torch.manual_seed(10)
    tiny_policy().save_pretrained(tmp_path / "model")

    def critic():
        return in_process(CriticWorker, str(tmp_path / "model"), config(lr=1e-2), 0.2)

    def train(worker, seeds):
        for seed in seeds:
            batch = make_batch(seed, size=4)
            batch["values"] = worker.compute_values(batch)
            batch["returns"] = torch.roll(batch["input_ids"], 1, 1).remainder(2).float() * batch[RESPONSE_MASK]
            worker.train_step(batch, float(batch[RESPONSE_MASK].sum()))

    straight = critic()
    train(straight, [11, 12, 13, 14])
    first = critic()
    train(first, [11, 12])
    first.save_checkpoint(str(tmp_path / "ckpt"))
    resumed = critic()
    resumed.load_checkpoint(str(tmp_path / "ckpt"))
    train(resumed, [13, 14])
    assert resumed.weights_digest() == straight.weights_digest()
    assert resumed.weights_digest() != first.weights_digest()
