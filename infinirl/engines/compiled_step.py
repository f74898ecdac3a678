"""The whole PPO optimizer step (forward, loss, backward, clipping, Adam) as one compiled function.

Why: a small policy's mini-batch step is a few hundred tiny tensor ops. On CPU each eager op (and
each autograd node, the gradient-clipping kernels and the optimizer's bookkeeping) costs more
interpreter overhead than arithmetic. Compiling only the loss (with its backward) removes that
overhead from the forward and backward passes; compiling the *whole* step removes it from the
clipping and the optimizer too, because the backward pass, the clipping and the Adam update then
fuse into the same few kernels.

How: the gradient is taken functionally (``torch.func.grad_and_value`` over
``torch.func.functional_call``), so dynamo traces forward and backward as one graph; gradient
clipping and Adam are written here as the same tensor math ``clip_grad_norm_`` and
``torch.optim.Adam`` do, updating the optimizer's own state tensors in place. The optimizer object
stays the source of truth (checkpoints, learning rate), so eager and compiled runs resume from each
other's checkpoints.

Semantics kept from the eager path:

* data-parallel ranks sum gradients between the backward pass and the clipping: with
  ``world_size > 1`` the step is two compiled functions (:func:`loss_and_grads`, :func:`clip_and_adam`)
  with the all-reduce between them; with one rank it is one;
* a parameter the loss does not reach (a value head under critic-free GRPO) gets a zero gradient
  here where eager autograd leaves ``None``: Adam's update of a zero gradient from zero moments is
  exactly zero, so the weights are the same (its optimizer state merely exists, all zeros).
"""

from __future__ import annotations

import contextlib
import math
import types
import weakref

import torch

from infinirl.engines.master_weights import MasterWeightAdam
from infinirl.runtime.compute_thread import on_compute_thread

__all__ = ["CompiledAdamStep", "adam_", "adam_corrections", "clip_by_total_norm", "inductor_options"]


def inductor_options(device: torch.device | str) -> dict:
    """Inductor options for compiling a small policy's hot path (a step, a decision) on ``device``.

    On CPU, ``cpp_wrapper``: the compiled graph's kernels are called from one generated C++
    function instead of a generated Python one, which removes most of the per-call interpreter
    overhead that dominates a small network's step and decision. The arithmetic is the same
    kernels'. On CUDA no option: the verified GPU path stays as it is."""
    return {"cpp_wrapper": True} if torch.device(device).type == "cpu" else {}


def clip_by_total_norm(grads: list[torch.Tensor], max_norm: float) -> tuple[list[torch.Tensor], torch.Tensor]:
    """``clip_grad_norm_``'s math, functional: the 2-norm over all gradients, and the gradients
    scaled by ``min(1, max_norm / (norm + 1e-6))``."""
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g, 2.0) for g in grads]), 2.0)
    scale = torch.clamp(max_norm / (norm + 1e-6), max=1.0)
    return [g * scale for g in grads], norm


def adam_corrections(count: int, lr: float, beta1: float, beta2: float) -> tuple[float, float]:
    """Adam's bias corrections after ``count`` steps, as ``torch.optim.Adam`` computes them (Python
    float64): ``(lr / (1 - beta1**count), sqrt(1 - beta2**count))``, the step size and the divisor
    of the second moment's square root."""
    return lr / (1 - beta1 ** count), math.sqrt(1 - beta2 ** count)


def adam_(params: list[torch.Tensor], grads: list[torch.Tensor], exp_avgs: list[torch.Tensor],
          exp_avg_sqs: list[torch.Tensor], steps: list[torch.Tensor], corrections: torch.Tensor,
          beta1: float, beta2: float, eps: float) -> None:
    """``torch.optim.Adam`` (no weight decay, no amsgrad), in place on its state tensors.

    ``corrections[i]`` holds parameter ``i``'s :func:`adam_corrections` for this step (float64,
    shape ``[len(params), 2]``), computed by the caller from the step counts. Why not from ``steps``
    in here: compiled, the two float64 ``pow`` of the bias corrections are recomputed for every
    vector of every parameter (inductor inlines scalar math into the loops that use it), which was
    a third of the whole step of a small policy; as an input they are two loads. ``steps`` are
    still counted here, in the optimizer's own state (checkpoints, eager resumes)."""
    for index, (param, grad, exp_avg, exp_avg_sq, step) in enumerate(zip(params, grads, exp_avgs, exp_avg_sqs, steps)):
        step.add_(1)
        exp_avg.lerp_(grad, 1 - beta1)
        exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step_size = corrections[index, 0].to(param.dtype)
        correction2_sqrt = corrections[index, 1].to(param.dtype)
        denom = exp_avg_sq.sqrt() / correction2_sqrt + eps
        param.sub_(step_size * exp_avg / denom)


def loss_and_grads(model, names: list[str], params: list[torch.Tensor], frozen: dict, model_args: tuple,
                   objective, objective_args: tuple) -> tuple[torch.Tensor, dict, list[torch.Tensor]]:
    """``objective(*outputs, *objective_args)`` with ``outputs = model(*model_args)``, as
    ``(loss, metrics)``, and the gradient of ``loss`` w.r.t. ``params`` (named ``names``)."""

    def loss_of(values):
        outputs = torch.func.functional_call(model, {**dict(zip(names, values)), **frozen}, model_args)
        return objective(*outputs, *objective_args)

    grads, (loss, metrics) = torch.func.grad_and_value(loss_of, has_aux=True)(params)
    return loss, metrics, list(grads)


def clip_and_adam(params, grads, exp_avgs, exp_avg_sqs, steps, corrections, max_norm: float, beta1: float,
                  beta2: float, eps: float) -> torch.Tensor:
    """Clip ``grads`` by their total norm, then one Adam step; returns the norm before clipping."""
    clipped, norm = clip_by_total_norm(grads, max_norm)
    adam_(params, clipped, exp_avgs, exp_avg_sqs, steps, corrections, beta1, beta2, eps)
    return norm


def whole_step(model, names, params, frozen, model_args, objective, objective_args, exp_avgs, exp_avg_sqs, steps,
               corrections, max_norm, beta1, beta2, eps):
    """One rank's whole step: :func:`loss_and_grads` then :func:`clip_and_adam`."""
    loss, metrics, grads = loss_and_grads(model, names, params, frozen, model_args, objective, objective_args)
    norm = clip_and_adam(params, grads, exp_avgs, exp_avg_sqs, steps, corrections, max_norm, beta1, beta2, eps)
    return loss, metrics, norm


_PER_MODEL: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _compiled(model: torch.nn.Module, fn, device_type: str):
    """``fn`` compiled for ``model`` alone, once per model, function and device type.

    Why per model: dynamo keeps its compiled graphs in a cache on the function's code object and
    picks one by its guards. Compiling a copy of ``fn``'s code object per model gives each model
    a cache of its own, holding only its graphs (one per mini-batch shape). That is what makes
    skipping the guards (``fixed_shapes``) safe: the entries left to choose from differ in their
    shapes, which the remaining guards tell apart, never in which model they were traced for (a
    model whose memory a later model reuses would otherwise match by its address).
    ``dynamic=False``: a run's mini-batch shapes never change."""
    compiled = _PER_MODEL.setdefault(model, {})
    key = (fn, device_type)
    if key not in compiled:
        own = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
        compiled[key] = torch.compile(own, dynamic=False, options=inductor_options(device_type))
    return compiled[key]


class CompiledAdamStep:
    """Steps ``model`` with ``optimizer`` (a plain ``torch.optim.Adam``) through compiled functions.

    Build one per update: it reads the optimizer's learning rate and state tensors once.

    :meth:`step` minimises ``objective(*model(*model_args), *objective_args)`` (which returns
    ``(loss, metrics)``). ``objective`` should be a module-level function: a fresh closure per call
    would make dynamo recompile. ``all_reduce_grads`` (data parallel) sums ``p.grad`` over ranks,
    as on the eager path; None with one rank.

    ``fixed_shapes=True`` promises that every step's arguments have the first step's structure,
    shapes, dtypes and devices (a PPO update's equal mini-batches). Steps after the first then
    skip dynamo's guard evaluation (``skip_guard_eval_unsafe``): the first step of each
    CompiledAdamStep evaluates every guard (and recompiles if the model or the shapes are new),
    and the later ones cannot differ from it in anything a guard checks, since they pass the same
    model, parameter and state tensors, objective and constants, and mini-batch views of the same
    shapes. Why: with one graph for forward, backward, clipping and Adam, the guards check every
    parameter and state tensor on every call, a sizeable share of a small policy's whole step.
    The stance is process-wide in torch, so the steps skip guards only on the process's compute
    thread (:func:`~infinirl.runtime.compute_thread.on_compute_thread`: a script's main thread, a
    Worker's sync-method thread), the one thread of our processes that calls compiled functions.
    """

    def __init__(self, model: torch.nn.Module, optimizer: torch.optim.Optimizer, objective, max_norm: float,
                 all_reduce_grads=None, fixed_shapes: bool = False):
        self.model, self.optimizer, self.objective = model, optimizer, objective
        self.fixed_shapes = fixed_shapes
        self._steps_taken = 0
        self.max_norm = float(max_norm)
        self.all_reduce_grads = all_reduce_grads
        if len(optimizer.param_groups) != 1:
            raise ValueError("the compiled step supports one optimizer parameter group")
        group = optimizer.param_groups[0]
        unsupported = {key: group.get(key) for key in ("weight_decay", "amsgrad", "maximize")
                       if group.get(key)}
        if isinstance(optimizer, MasterWeightAdam):
            raise ValueError("bf16/fp16 trainable weights step through float32 master copies "
                             "(engines.master_weights), which the compiled step does not keep: set actor.compile=false")
        if type(optimizer) is not torch.optim.Adam or unsupported:
            raise ValueError(f"the compiled step implements plain Adam; got {type(optimizer).__name__} with "
                             f"{unsupported or 'its defaults'}: use actor.compile=false for other optimizers")
        self.beta1, self.beta2 = (float(b) for b in group["betas"])
        self.eps = float(group["eps"])
        trainable = {id(p) for p in group["params"] if p.requires_grad}
        named = [(n, p) for n, p in model.named_parameters() if id(p) in trainable]
        self.names = [n for n, _ in named]
        self.params = [p for _, p in named]
        trained = {id(p) for p in self.params}
        self.frozen = {n: p.detach() for n, p in model.named_parameters() if id(p) not in trained}
        self.frozen.update(dict(model.named_buffers()))
        self._values = [p.detach() for p in self.params]  # same storage: updated in place
        state = [self._adam_state(p) for p in self.params]
        self._exp_avgs = [s["exp_avg"] for s in state]
        self._exp_avg_sqs = [s["exp_avg_sq"] for s in state]
        self._steps = [s["step"] for s in state]
        # Read once: the learning rate is fixed within an update (the schedule moves it between
        # iterations). Each step's bias corrections go in through one float64 tensor, rewritten in
        # place (through its numpy view, no torch dispatch): a new value never recompiles.
        self._lr = float(group["lr"])
        self._counts = [int(step) for step in self._steps]
        self._corrections = torch.zeros(len(self.params), 2, dtype=torch.float64)
        self._corrections_view = self._corrections.numpy()
        self._device_type = self.params[0].device.type if self.params else "cpu"

    def _next_corrections(self) -> torch.Tensor:
        """Count this step for every parameter and write its :func:`adam_corrections`."""
        memo: dict[int, tuple[float, float]] = {}
        for index, count in enumerate(self._counts):
            count += 1
            self._counts[index] = count
            if count not in memo:
                memo[count] = adam_corrections(count, self._lr, self.beta1, self.beta2)
            self._corrections_view[index] = memo[count]
        if self._device_type == "cpu":
            return self._corrections
        # On an accelerator the corrections go in on the parameters' device: inductor would pass a
        # CPU tensor's pointer straight into a GPU kernel (CUDA fails with "invalid argument").
        # A fresh pinned copy per step, copied asynchronously: the caching host
        # allocator keeps it until the copy is done, so the next step's rewrite cannot race it.
        return self._corrections.pin_memory().to(self.params[0].device, non_blocking=True)

    def _adam_state(self, param: torch.Tensor) -> dict:
        """The optimizer's state of ``param``, created as ``torch.optim.Adam`` creates it."""
        state = self.optimizer.state[param]
        if not state:
            fused = bool(self.optimizer.param_groups[0].get("fused"))
            state["step"] = (torch.zeros((), dtype=torch.float32, device=param.device) if fused
                             else torch.tensor(0.0, dtype=torch.float32))
            state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
        return state

    def step(self, model_args: tuple, objective_args: tuple) -> tuple[torch.Tensor, dict, torch.Tensor]:
        """One optimizer step on this mini-batch; ``(loss, metrics, grad_norm)`` (detached)."""
        # torch keeps the stance process-wide: only the process's compute thread (a script's main
        # thread, a Worker's sync-method thread) changes it; ranks simulated by threads keep guards.
        trusted = self.fixed_shapes and self._steps_taken > 0 and on_compute_thread()
        self._steps_taken += 1
        with torch.compiler.set_stance("default", skip_guard_eval_unsafe=True) if trusted else contextlib.nullcontext():
            return self._step(model_args, objective_args)

    def _step(self, model_args: tuple, objective_args: tuple) -> tuple[torch.Tensor, dict, torch.Tensor]:
        exp_avgs, exp_avg_sqs, steps = self._exp_avgs, self._exp_avg_sqs, self._steps
        corrections = self._next_corrections()
        if self.all_reduce_grads is None:
            step = _compiled(self.model, whole_step, self._device_type)
            return step(self.model, self.names, self._values, self.frozen, model_args, self.objective, objective_args,
                        exp_avgs, exp_avg_sqs, steps, corrections, self.max_norm, self.beta1, self.beta2, self.eps)
        loss, metrics, grads = _compiled(self.model, loss_and_grads, self._device_type)(
            self.model, self.names, self._values, self.frozen, model_args, self.objective, objective_args)
        for param, grad in zip(self.params, grads):  # the eager path's hand-off: sum p.grad over ranks
            param.grad = grad
        self.all_reduce_grads()
        grads = [param.grad for param in self.params]
        for param in self.params:
            param.grad = None
        norm = _compiled(self.model, clip_and_adam, self._device_type)(
            self._values, grads, exp_avgs, exp_avg_sqs, steps, corrections, self.max_norm, self.beta1, self.beta2,
            self.eps)
        return loss, metrics, norm
