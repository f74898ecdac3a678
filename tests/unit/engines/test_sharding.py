"""FSDP2 sharding with summed gradients (``infinirl.engines.sharding``): sharded modules return no
view tensors, so FSDP2 has nothing to warn about and an in-place op on a layer's output keeps its
pre-backward hook; the gradients of two gloo ranks equal a float64 unsharded reference."""

from __future__ import annotations

import os
import socket
import warnings

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn

from infinirl.engines.distributed import init_distributed
from infinirl.engines.sharding import full_tensor, outputs_without_views, shard

VIEW_WARNING = "returned a view tensor"


class Block(nn.Module):
    """A biased linear layer on ``[B, T, F]`` inputs: ``addmm`` on the flattened rows, viewed back."""

    def __init__(self, width: int):
        super().__init__()
        self.linear = nn.Linear(width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(x)


class Tower(nn.Module):
    """Two blocks sharded as groups of their own (``_no_split_modules``), each output changed in place."""

    _no_split_modules = ["Block"]

    def __init__(self, width: int = 6):
        super().__init__()
        self.blocks = nn.ModuleList([Block(width), Block(width)])
        self.head = nn.Linear(width, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for block in self.blocks:
            x = block(x)
            x += 0.5  # in place on the block's output: the hazard FSDP2 warns about
            x = torch.tanh(x)
        return self.head(x)


def batch(rank: int) -> torch.Tensor:
    return torch.randn(3, 4, 6, generator=torch.Generator().manual_seed(10 + rank))


def loss_of(model: nn.Module, x: torch.Tensor) -> torch.Tensor:
    return (model(x) ** 2).sum()


def reference_grads() -> dict[str, torch.Tensor]:
    """float64, unsharded, both ranks' batches: the gradient the two ranks' sum must equal."""
    torch.manual_seed(0)
    model = Tower().double()
    sum(loss_of(model, batch(rank).double()) for rank in range(2)).backward()
    return {name: p.grad for name, p in model.named_parameters()}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def two_rank_worker(rank: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2")
    torch.set_num_threads(1)
    init_distributed()
    try:
        torch.manual_seed(0)
        model = shard(Tower())
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for _ in range(2):  # a second step: the hooks of the first are gone, the state is reset
                model.zero_grad(set_to_none=True)
                loss_of(model, batch(rank)).backward()
        grads = {name: full_tensor(p.grad).detach().clone() for name, p in model.named_parameters()}
        if rank == 0:
            torch.save({"grads": grads, "warnings": [str(w.message) for w in caught]},
                       os.path.join(out_dir, "rank0.pt"))
    finally:
        dist.destroy_process_group()


def test_two_ranks_sum_the_float64_gradient_despite_in_place_ops_on_layer_outputs(tmp_path):
    mp.spawn(two_rank_worker, args=(free_port(), str(tmp_path)), nprocs=2, join=True)
    result = torch.load(tmp_path / "rank0.pt", weights_only=False)
    assert not [message for message in result["warnings"] if VIEW_WARNING in message]
    expected = reference_grads()
    assert result["grads"].keys() == expected.keys()
    for name, grad in result["grads"].items():
        torch.testing.assert_close(grad.double(), expected[name], atol=1e-5, rtol=0, msg=name)


def test_views_are_copied_only_when_they_need_a_gradient():
    weight = torch.randn(4, 3, requires_grad=True)
    view = (weight * 2).view(3, 4)
    plain = weight * 3
    frozen = torch.randn(4, 3).view(3, 4)
    output = outputs_without_views(None, (), {"a": view, "b": (plain, [frozen])})
    assert output["a"]._base is None and torch.equal(output["a"], view)
    assert output["b"][0] is plain and output["b"][1][0] is frozen
    with torch.no_grad():
        assert outputs_without_views(None, (), view) is None  # no-grad forwards are left alone
