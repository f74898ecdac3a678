"""Data-parallel strategies (``engines.parallel``): chosen by name; two gloo ranks sum their
gradients (``ddp``); a checkpoint written by either strategy restores model and optimizer exactly,
atomically; the full weights are the model's, unsharded."""

from __future__ import annotations

import os
import socket

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn

from infinirl.engines.distributed import init_distributed
from infinirl.engines.master_weights import MasterWeightAdam
from infinirl.engines.parallel import DATA_PARALLEL, FullyShardedDataParallel, ReplicatedDataParallel
from infinirl.registry import UnknownNameError


@pytest.fixture(scope="module", autouse=True)
def one_rank_group():
    created = init_distributed()
    yield
    if created:
        dist.destroy_process_group()


def build() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 2))


def step(model: nn.Module, optimizer: torch.optim.Optimizer, seed: int) -> None:
    x = torch.randn(5, 3, generator=torch.Generator().manual_seed(seed))
    optimizer.zero_grad(set_to_none=True)
    (model(x) ** 2).sum().backward()
    optimizer.step()


def test_strategies_are_chosen_by_name_and_a_typo_lists_them():
    assert DATA_PARALLEL.names() == ["ddp", "fsdp"]
    assert DATA_PARALLEL.get("ddp") is ReplicatedDataParallel
    assert DATA_PARALLEL.get("fsdp") is FullyShardedDataParallel
    with pytest.raises(UnknownNameError, match="unknown data-parallel strategy 'fdsp'; registered: ddp, fsdp"):
        DATA_PARALLEL.get("fdsp")
    assert ReplicatedDataParallel.whole_step is not None and FullyShardedDataParallel.whole_step is None
    assert not ReplicatedDataParallel(0, 1).needs_process_group and ReplicatedDataParallel(0, 2).needs_process_group
    assert FullyShardedDataParallel(0, 1).needs_process_group


@pytest.mark.parametrize("name", ["ddp", "fsdp"])
def test_a_checkpoint_restores_model_and_optimizer_exactly(name, tmp_path):
    strategy = DATA_PARALLEL.get(name)(0, 1)
    model = strategy.wrap(build())
    optimizer = strategy.build_optimizer(model, lr=1e-2, eps=1e-5)
    step(model, optimizer, 1)
    file = tmp_path / "actor.pt"
    strategy.save_checkpoint(model, optimizer, file)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["actor.pt"]  # no temporary file left
    saved = {key: tensor.clone() for key, tensor in strategy.full_weights(model)}
    step(model, optimizer, 2)
    expected = {key: tensor.clone() for key, tensor in strategy.full_weights(model)}

    restored_model = strategy.wrap(build())
    restored_optimizer = strategy.build_optimizer(restored_model, lr=1e-2, eps=1e-5)
    strategy.load_checkpoint(restored_model, restored_optimizer, file, torch.device("cpu"))
    for key, tensor in strategy.full_weights(restored_model):
        assert torch.equal(tensor, saved[key]), key
    step(restored_model, restored_optimizer, 2)  # the optimizer state came back too: the same next step
    for key, tensor in strategy.full_weights(restored_model):
        assert torch.equal(tensor, expected[key]), key


def test_sharded_full_weights_are_the_plain_model_s():
    plain = build()
    sharded = FullyShardedDataParallel(0, 1).wrap(build())
    weights = dict(FullyShardedDataParallel(0, 1).full_weights(sharded))
    assert weights.keys() == plain.state_dict().keys()
    for key, tensor in plain.state_dict().items():
        assert not hasattr(weights[key], "full_tensor") and torch.equal(weights[key], tensor)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def ddp_rank(rank: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2")
    torch.set_num_threads(1)
    init_distributed()
    try:
        strategy = ReplicatedDataParallel(rank, 2)
        model = build()
        for index, p in enumerate(model.parameters()):
            p.grad = torch.full_like(p, float(10 * rank + index))
        strategy.reduce_gradients(model)
        if rank == 0:
            torch.save([p.grad for p in model.parameters()], os.path.join(out_dir, "grads.pt"))
    finally:
        dist.destroy_process_group()


def test_ddp_sums_the_gradients_of_two_ranks(tmp_path):
    mp.spawn(ddp_rank, args=(free_port(), str(tmp_path)), nprocs=2, join=True)
    grads = torch.load(tmp_path / "grads.pt")
    for index, grad in enumerate(grads):
        assert torch.equal(grad, torch.full_like(grad, float(index + (10 + index))))


def bf16_linear() -> nn.Linear:
    """Weights near 0.01 (bf16 spacing ~6e-5), where 20 Adam steps of 5e-6 move a float32 weight by an ulp or two."""
    torch.manual_seed(0)
    linear = nn.Linear(16, 16)
    with torch.no_grad():
        for p in linear.parameters():
            p.copy_(p.sign() * (0.008 + 0.004 * torch.rand_like(p)))
    return linear.to(torch.bfloat16)


def bf16_step(model: nn.Module, optimizer: torch.optim.Optimizer, seed: int) -> None:
    x = torch.randn(8, 16, generator=torch.Generator().manual_seed(seed))
    optimizer.zero_grad(set_to_none=True)
    (model(x.to(torch.bfloat16)).float() ** 2).sum().backward()
    optimizer.step()


@pytest.mark.parametrize("name", ["ddp", "fsdp"])
def test_bf16_weights_train_through_float32_masters_and_resume_exactly(name, tmp_path):
    """At lr 5e-6 Adam's steps are far below bf16's spacing: stepped in place the weights never move.
    The optimizer steps float32 masters (the same updates as float32 Adam given the same gradients) and
    hands the parameters their rounding; a checkpoint carries the masters, so resuming is exact."""
    strategy = DATA_PARALLEL.get(name)(0, 1)
    model = strategy.wrap(bf16_linear())
    optimizer = strategy.build_optimizer(model, lr=5e-6, eps=1e-8)
    reference = bf16_linear().float()  # the same initial values, in float32
    reference_optimizer = torch.optim.Adam(reference.parameters(), lr=5e-6, eps=1e-8)
    in_place = bf16_linear()  # the same steps on the bf16 weights themselves
    in_place_optimizer = torch.optim.Adam(in_place.parameters(), lr=5e-6, eps=1e-8)
    for seed in range(20):
        bf16_step(in_place, in_place_optimizer, seed)
    for seed in range(20):
        bf16_step(model, optimizer, seed)
        # the reference steps with the very gradients the bf16 model got, cast up
        for mine, ref in zip(model.parameters(), reference.parameters(), strict=True):
            grad = mine.grad.full_tensor() if hasattr(mine.grad, "full_tensor") else mine.grad
            ref.grad = grad.float()
        reference_optimizer.step()
    weights = dict(strategy.full_weights(model))
    for key, tensor in reference.state_dict().items():
        assert weights[key].dtype == torch.bfloat16
        assert torch.equal(weights[key], tensor.to(torch.bfloat16)), key  # the float32 run, rounded
        moved = weights[key] != bf16_linear().state_dict()[key]
        assert moved.float().mean() > 0.5, key  # most weights moved by the float32 run's amount
        assert torch.equal(in_place.state_dict()[key], bf16_linear().state_dict()[key]), key  # stuck without masters

    file = tmp_path / "actor.pt"
    strategy.save_checkpoint(model, optimizer, file)
    bf16_step(model, optimizer, 100)
    expected = {key: tensor.clone() for key, tensor in strategy.full_weights(model)}
    restored = strategy.wrap(bf16_linear())
    restored_optimizer = strategy.build_optimizer(restored, lr=5e-6, eps=1e-8)
    strategy.load_checkpoint(restored, restored_optimizer, file, torch.device("cpu"))
    bf16_step(restored, restored_optimizer, 100)
    for key, tensor in strategy.full_weights(restored):
        assert torch.equal(tensor, expected[key]), key


def test_float32_models_keep_plain_adam():
    assert type(ReplicatedDataParallel(0, 1).build_optimizer(build(), lr=1e-3, eps=1e-8)) is torch.optim.Adam
    assert type(ReplicatedDataParallel(0, 1).build_optimizer(bf16_linear(), lr=1e-3, eps=1e-8)) is MasterWeightAdam
