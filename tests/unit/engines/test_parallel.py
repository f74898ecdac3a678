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
