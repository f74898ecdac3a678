"""The compiled optimizer step's pieces (``infinirl.engines.compiled_step``) against slow
references: gradient clipping against a float64 loop and ``clip_grad_norm_``, the Adam update
against a float64 loop and ``torch.optim.Adam``; and the compiled step on a small module against
the eager ``backward`` / ``clip_grad_norm_`` / ``Adam.step`` sequence."""

import math

import pytest
import torch

from infinirl.engines.compiled_step import (
    CompiledAdamStep,
    adam_,
    adam_corrections,
    clip_by_total_norm,
    inductor_options,
)
from infinirl.runners.embodied_config import find_cxx_compiler


def grads_of(seed: int, scale: float) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return [scale * torch.randn(shape, generator=gen) for shape in ((3, 4), (4,), (1,))]


@pytest.mark.parametrize("scale", [1e-3, 1.0, 30.0])  # below, around and above max_norm
def test_clipping_matches_a_float64_loop_and_clip_grad_norm(scale):
    grads, max_norm = grads_of(0, scale), 0.5
    clipped, norm = clip_by_total_norm(grads, max_norm)

    squares = 0.0
    for g in grads:
        for x in g.double().reshape(-1).tolist():
            squares += x * x
    total = math.sqrt(squares)
    factor = min(1.0, max_norm / (total + 1e-6))
    assert float(norm) == pytest.approx(total, rel=1e-6)
    for got, g in zip(clipped, grads):
        torch.testing.assert_close(got.double(), g.double() * factor, rtol=1e-6, atol=0)

    params = [torch.nn.Parameter(torch.zeros_like(g)) for g in grads]
    for p, g in zip(params, grads):
        p.grad = g.clone()
    torch_norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
    assert float(torch_norm) == pytest.approx(float(norm), rel=1e-6)
    for p, got in zip(params, clipped):
        torch.testing.assert_close(p.grad, got, rtol=1e-6, atol=0)


def test_adam_matches_a_float64_loop_and_torch_adam():
    lr, beta1, beta2, eps = 1e-2, 0.9, 0.999, 1e-5
    start = grads_of(1, 1.0)
    ours = [p.clone() for p in start]
    state = [(torch.zeros_like(p), torch.zeros_like(p), torch.tensor(0.0)) for p in ours]
    reference = [p.double().reshape(-1).tolist() for p in start]
    moments = [([0.0] * len(r), [0.0] * len(r)) for r in reference]
    torch_params = [torch.nn.Parameter(p.clone()) for p in start]
    torch_adam = torch.optim.Adam(torch_params, lr=lr, betas=(beta1, beta2), eps=eps, foreach=False)
    for t in range(1, 6):
        grads = grads_of(10 + t, 1.0)
        corrections = torch.tensor([adam_corrections(t, lr, beta1, beta2)] * len(ours), dtype=torch.float64)
        adam_(ours, grads, [s[0] for s in state], [s[1] for s in state], [s[2] for s in state],
              corrections, beta1, beta2, eps)
        for values, (m, v), g in zip(reference, moments, grads):  # the textbook update, element by element
            for i, gi in enumerate(g.double().reshape(-1).tolist()):
                m[i] = beta1 * m[i] + (1 - beta1) * gi
                v[i] = beta2 * v[i] + (1 - beta2) * gi * gi
                m_hat, v_hat_sqrt = m[i] / (1 - beta1 ** t), math.sqrt(v[i]) / math.sqrt(1 - beta2 ** t)
                values[i] -= lr * m_hat / (v_hat_sqrt + eps)
        for p, g in zip(torch_params, grads):
            p.grad = g.clone()
        torch_adam.step()
    for got, want, p in zip(ours, reference, torch_params):
        torch.testing.assert_close(got.double().reshape(-1), torch.tensor(want, dtype=torch.float64),
                                   rtol=0, atol=1e-6)
        torch.testing.assert_close(got, p.detach(), rtol=0, atol=1e-7)
    assert [float(s[2]) for s in state] == [5.0, 5.0, 5.0]


def test_adam_corrections_are_the_textbook_bias_corrections():
    step_size, divisor = adam_corrections(7, 3e-4, 0.9, 0.999)
    assert step_size == pytest.approx(3e-4 / (1 - 0.9 ** 7), rel=1e-15)
    assert divisor == pytest.approx(math.sqrt(1 - 0.999 ** 7), rel=1e-15)


def test_cpu_compiles_call_their_kernels_from_cpp_and_cuda_keeps_inductors_defaults():
    assert inductor_options("cpu") == inductor_options(torch.device("cpu")) == {"cpp_wrapper": True}
    assert inductor_options("cuda:0") == {}


def objective(prediction, target, unused_rows):
    loss = ((prediction - target) ** 2).mean()
    return loss, {"mse": loss.detach()}


class Net(torch.nn.Module):
    """Two layers plus one that the loss never reaches (as a value head under critic-free GRPO)."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.body, self.head, self.unused = torch.nn.Linear(3, 8), torch.nn.Linear(8, 1), torch.nn.Linear(3, 1)

    def forward(self, x):
        return (self.head(torch.tanh(self.body(x))).squeeze(-1),)


@pytest.mark.skipif(find_cxx_compiler() is None,
                    reason="torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")
def test_the_compiled_step_steps_like_eager_backward_clip_and_adam():
    from torch._dynamo.utils import counters

    gen = torch.Generator().manual_seed(3)
    x, y = torch.randn(16, 3, generator=gen), torch.randn(16, generator=gen)
    eager, compiled = Net(), Net()
    eager_opt = torch.optim.Adam(eager.parameters(), lr=1e-2, eps=1e-5, fused=True)
    compiled_opt = torch.optim.Adam(compiled.parameters(), lr=1e-2, eps=1e-5, fused=True)
    counters.clear()
    for _ in range(4):
        loss, _ = objective(*eager(x), y, None)
        eager_opt.zero_grad(set_to_none=True)
        loss.backward()
        eager_norm = torch.nn.utils.clip_grad_norm_(list(eager.parameters()), 0.5, foreach=True)
        eager_opt.step()
        step = CompiledAdamStep(compiled, compiled_opt, objective, 0.5)
        compiled_loss, metrics, norm = step.step((x,), (y, None))
        assert float(norm) == pytest.approx(float(eager_norm), rel=1e-5)
        assert float(metrics["mse"]) == pytest.approx(float(loss.detach()), rel=1e-5)
    for a, b in zip(compiled.parameters(), eager.parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    assert not torch.equal(compiled.body.weight, Net().body.weight)  # it trained
    assert torch.equal(compiled.unused.weight, Net().unused.weight)  # unreached: unchanged
    # the optimizer object holds the state, in torch's own layout (checkpoints work either way)
    assert float(compiled_opt.state[compiled.body.weight]["step"]) == 4.0
    torch.testing.assert_close(compiled_opt.state[compiled.body.weight]["exp_avg"],
                               eager_opt.state[eager.body.weight]["exp_avg"], rtol=0, atol=1e-6)
    assert counters["stats"]["unique_graphs"] == 1 and not counters["graph_break"]  # one graph, reused


@pytest.mark.skipif(find_cxx_compiler() is None,
                    reason="torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")
def test_fixed_shape_steps_skip_guards_only_after_each_updates_first_step():
    """``fixed_shapes=True`` (what a PPO update passes): within one CompiledAdamStep the steps after
    the first skip dynamo's guards. The next update's first step evaluates them again, so a new
    mini-batch shape compiles its own graph instead of running the old one. Every step matches
    eager backward / clip / Adam."""
    fixed_shape_updates_step_like_eager("cpu")


def fixed_shape_updates_step_like_eager(device: str) -> None:
    """Three updates of three fixed-shape steps on ``device`` (the third update's mini-batches are
    smaller), each step against eager backward / clip / Adam; two graphs, one per shape. Shared
    with the GPU check (tests/gpu/test_embodied_gpu.py)."""
    from torch._dynamo.utils import counters

    gen = torch.Generator().manual_seed(5)
    eager, compiled = Net().to(device), Net().to(device)
    eager_opt = torch.optim.Adam(eager.parameters(), lr=1e-2, eps=1e-5, fused=True)
    compiled_opt = torch.optim.Adam(compiled.parameters(), lr=1e-2, eps=1e-5, fused=True)
    counters.clear()
    for rows in (16, 16, 10):
        step = CompiledAdamStep(compiled, compiled_opt, objective, 0.5, fixed_shapes=True)
        for _ in range(3):
            x, y = torch.randn(rows, 3, generator=gen).to(device), torch.randn(rows, generator=gen).to(device)
            loss, _ = objective(*eager(x), y, None)
            eager_opt.zero_grad(set_to_none=True)
            loss.backward()
            eager_norm = torch.nn.utils.clip_grad_norm_(list(eager.parameters()), 0.5, foreach=True)
            eager_opt.step()
            _, metrics, norm = step.step((x,), (y, None))
            assert float(metrics["mse"]) == pytest.approx(float(loss.detach()), rel=1e-5)
            assert float(norm) == pytest.approx(float(eager_norm), rel=1e-5)
            for a, b in zip(compiled.parameters(), eager.parameters()):
                torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    assert all(p.device.type == torch.device(device).type for p in compiled.parameters())
    assert counters["stats"]["unique_graphs"] == 2  # one per mini-batch shape


@pytest.mark.skipif(find_cxx_compiler() is None,
                    reason="torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")
def test_the_compiled_step_continues_an_eager_optimizer_from_its_step_counts():
    """Eager steps first (the unreached layer gets no gradient, so no Adam state), then compiled
    steps on the same optimizer: each parameter's bias corrections continue from its own count."""
    gen = torch.Generator().manual_seed(4)
    x, y = torch.randn(16, 3, generator=gen), torch.randn(16, generator=gen)
    eager, mixed = Net(), Net()
    eager_opt = torch.optim.Adam(eager.parameters(), lr=1e-2, eps=1e-5, fused=True)
    mixed_opt = torch.optim.Adam(mixed.parameters(), lr=1e-2, eps=1e-5, fused=True)

    def eager_step(net, opt):
        loss, _ = objective(*net(x), y, None)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_([p for p in net.parameters() if p.grad is not None], 0.5, foreach=True)
        opt.step()

    for _ in range(5):
        eager_step(eager, eager_opt)
    for _ in range(3):
        eager_step(mixed, mixed_opt)
    assert mixed.unused.weight not in mixed_opt.state or not mixed_opt.state[mixed.unused.weight]
    step = CompiledAdamStep(mixed, mixed_opt, objective, 0.5)
    for _ in range(2):
        step.step((x,), (y, None))
    for a, b in zip(mixed.parameters(), eager.parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    assert float(mixed_opt.state[mixed.body.weight]["step"]) == 5.0
    assert float(mixed_opt.state[mixed.unused.weight]["step"]) == 2.0  # created by the compiled step at 0


def test_the_compiled_step_refuses_an_optimizer_it_does_not_implement():
    net = Net()
    with pytest.raises(ValueError, match="plain Adam.*actor.compile=false"):
        CompiledAdamStep(net, torch.optim.SGD(net.parameters(), lr=0.1), objective, 0.5)
    with pytest.raises(ValueError, match="weight_decay"):
        CompiledAdamStep(net, torch.optim.Adam(net.parameters(), weight_decay=0.1), objective, 0.5)
