"""The embodied PPO update: the PPO-clip objective of a policy over env decisions, and its epochs
of mini-batch steps.

The same update serves PPO (GAE advantages, value head trained) and embodied GRPO (group-normalised
episode returns, ``critic=False``: no value loss, and the batch's ``advantage_mask`` drops the
decisions after each env's first episode end from every loss term).

Split-invariance: each data-parallel rank trains on *its share of every mini-batch*. Mini-batch
membership comes from the caller's generator (identical on every rank and on a resumed run);
per-mini-batch advantage normalisation uses the statistics of the whole mini-batch, and every loss
term is a sum over this rank's rows divided by a *mini-batch-global* count
(:func:`~infinirl.algorithms.aggregation.aggregate`), so the gradients summed over ranks equal the
single-process gradient: the update is independent of the number of ranks.

How gradients are summed over ranks and whether the whole optimizer step is compiled belong to the
training backend (:mod:`infinirl.engines.parallel`); :func:`ppo_update` takes both as arguments.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from infinirl.algorithms.aggregation import aggregate
from infinirl.algorithms.losses import entropy_loss, ppo_clip_loss, value_loss
from infinirl.algorithms.masking import masked_mean
from infinirl.algorithms.metrics import metric_reduction

__all__ = ["KL_SHARE", "PPOSpec", "compiled_minibatch_loss", "critic_parameter_ids", "inner_policy",
           "joint_chunk_logprob", "mini_batch_kl", "ppo_minibatch_loss",
           "ppo_objective", "ppo_objective_of_outputs", "ppo_update"]


@dataclass(frozen=True, kw_only=True)
class PPOSpec:
    """PPO hyperparameters (documented on the runner's config fields)."""

    lr: float = 3e-4
    value_lr: float | None = None
    """The critic's learning rate (the policy's ``critic_modules``); None: ``lr``."""
    anneal_lr: bool = True
    total_iterations: int = 1
    epochs: int = 10
    mini_batches: int = 32
    clip: float = 0.2
    value_clip: float | None = None
    value_coef: float = 0.5
    entropy_coef: float = 0.0
    max_grad_norm: float = 0.5
    normalize_advantages: bool = True
    gae_level: str = "chunk"
    adam_eps: float = 1e-5
    strategy: str = "ddp"
    """The data-parallel strategy of the actor (:data:`infinirl.engines.parallel.DATA_PARALLEL`)."""
    seed: int = 0
    critic: bool = True
    """Train the value head (PPO). False (GRPO): no value loss is computed, the head stays as built."""
    is_cap: float | None = None
    """Off-policy correction (asynchronous training): before the epochs, the log-probs of the batch
    under the current weights are recomputed (the *proximal* policy, PPO's trust-region centre) and
    every decision is reweighted by ``pi_proximal / pi_behaviour`` (the rollout's version), capped
    at ``is_cap``: decoupled PPO, per action chunk at chunk level (a chunk's log-prob as PPO takes
    it, see ``joint_chunk``) or per action at action level."""
    is_cap_mode: str = "truncate"
    """truncate (TIS, min(w, cap)) | mask (MIS: decisions with w > cap get no policy gradient)."""
    desired_kl: float | None = None
    """Adapt the rate after every mini-batch to keep PPO's approximate KL near this (None: off)."""
    critic_warmup: int = 0
    """Iterations ``0 .. critic_warmup - 1`` train the critic only (:func:`ppo_update`)."""
    warmup_steps: int = 0
    """Ramp the policy's rate linearly over its first ``warmup_steps`` optimizer steps (:func:`_ramp_rates`)."""
    joint_chunk: bool = False
    """Not a config key: :func:`ppo_update` sets it from the policy (``Policy.joint_chunk_logprob``).
    At chunk level a decision's log-prob (and its entropy) is the sum over all ``K`` rows of the
    chunk, executed or not: a flow policy's path likelihood, as it denoises the chunk jointly.
    False: the sum over the executed rows (each row its own action's likelihood). ``step_mask``
    then only shapes the rewards and advantages. At action level every row is a decision either way."""
    compile: bool = False
    """Compile each mini-batch's optimizer step where the strategy allows it (the whole step,
    :class:`~infinirl.engines.compiled_step.CompiledAdamStep`), else the forward pass and loss
    (:func:`compiled_minibatch_loss`)."""


def _rows(value: Any, index: torch.Tensor | slice) -> Any:
    if isinstance(value, dict):
        return {k: _rows(v, index) for k, v in value.items()}
    if not isinstance(value, torch.Tensor):  # a text field (numpy strings, one per row): index on the host
        return value[index.cpu().numpy() if isinstance(index, torch.Tensor) else index]
    return value[index]


def _no_reduction() -> None:
    """One rank: nothing to sum the gradients with."""


#: ``whole_step(model, optimizer, objective, max_norm, all_reduce_grads)`` builds an object whose
#: ``step(model_args, objective_args)`` takes one whole optimizer step and returns
#: ``(loss, metrics, grad_norm)``; ``all_reduce_grads`` is None with one rank.
WholeStepFactory = Callable[..., Any]


def ppo_update(model, optimizer, batch: dict, iteration: int, ppo: PPOSpec, rank: int = 0, world_size: int = 1,
               all_reduce_grads: Callable[[], None] = _no_reduction, *, generator: torch.Generator,
               whole_step: WholeStepFactory | None = None,
               anchor: Callable[[int], tuple[torch.Tensor, dict]] | None = None) -> dict:
    """The PPO epochs of one iteration on ``model`` (a ``NormalizedPolicy``, possibly sharded).

    ``batch`` (tensors, flat over ``B = T * N`` decisions): ``obs`` dict, ``actions``
    ``[B, C, ...]``, ``logprobs`` / ``step_mask`` ``[B, C]``, ``values`` ``[B]``, ``advantages`` /
    ``returns`` ``[B]`` (chunk level) or ``[B, C]`` (action level), optional ``extras``, optional
    ``advantage_mask`` shaped like ``advantages`` (the estimator's mask; all true if absent):
    decisions outside it count in no loss term and in no normaliser (policy loss, entropy,
    per-mini-batch advantage statistics).

    ``generator`` (a CPU generator, the same state on every rank) draws each epoch's mini-batch
    order. ``all_reduce_grads()`` sums ``p.grad`` over ranks after each backward pass.
    ``whole_step`` (see :data:`WholeStepFactory`): with ``ppo.compile``, the factory of the compiled
    whole optimizer step; None where the model cannot be compiled whole (then only the loss is).
    ``anchor(step)`` (optional; eager steps only): a further loss term and its metrics for optimizer
    step ``step`` (0-based within the update), added to the PPO loss of that step once the policy
    trains (PPO's behaviour-cloning anchor, :mod:`infinirl.components.demo_anchor`).
    """
    ppo = dataclasses.replace(ppo, joint_chunk=joint_chunk_logprob(model))
    factor = max(0.0, 1.0 - iteration / max(1, ppo.total_iterations)) if ppo.anneal_lr else 1.0
    if ppo.anneal_lr or ppo.desired_kl is not None or ppo.warmup_steps:
        _set_rates(optimizer, ppo, factor)
    size = batch["actions"].shape[0]
    per_mini = size // ppo.mini_batches
    device = batch["advantages"].device
    keep_all = (batch["advantage_mask"].to(torch.float32) if "advantage_mask" in batch
                else torch.ones(batch["advantages"].shape, dtype=torch.float32, device=device))
    params = [p for p in model.parameters() if p.requires_grad]
    warmup = ppo.critic and iteration < ppo.critic_warmup
    critic = critic_parameter_ids(model) if ppo.critic else set()
    parts = _GradParts(params=params, critic=[p for p in params if id(p) in critic],
                       policy=[p for p in params if id(p) not in critic], max_norm=ppo.max_grad_norm)
    if warmup:  # the critic alone: no step for any parameter outside it (no policy or entropy term reaches it)
        parts = dataclasses.replace(parts, frozen=tuple(parts.policy))
    if ppo.is_cap is not None:  # decoupled PPO: clip around the trainer's own (proximal) policy
        batch = {**batch, "behaviour_logprobs": batch["logprobs"],
                 "logprobs": proximal_logprobs(model, batch, per_mini)}
    minibatch_loss = compiled_minibatch_loss(ppo.compile)
    stepper = (whole_step(model, optimizer, ppo_objective_of_outputs, ppo.max_grad_norm,
                          all_reduce_grads if world_size > 1 else None)
               if ppo.compile and whole_step is not None and not warmup else None)
    step_metrics: dict[str, list[torch.Tensor]] = {}
    # The observation statistics are fixed during the update (folded in after it): normalise the
    # whole batch once instead of every mini-batch (identical values, fewer small ops per step).
    normalize = getattr(model, "normalize", None)
    obs = normalize(batch["obs"]) if normalize is not None else batch["obs"]
    columns = {"obs": obs, "actions": batch["actions"], "logprobs": batch["logprobs"],
               "values": batch["values"], "returns": batch["returns"],
               "advantages": batch["advantages"].to(torch.float32), "keep": keep_all,
               "step_mask": batch["step_mask"].to(torch.float32)}
    row_keys = ("logprobs", "values", "returns")
    if "behaviour_logprobs" in batch:
        columns["behaviour_logprobs"] = batch["behaviour_logprobs"]
        row_keys += ("behaviour_logprobs",)
    if "extras" in batch:
        columns["extras"] = batch["extras"]
    for epoch in range(ppo.epochs):
        order = torch.randperm(size, generator=generator).to(device)  # drawn on CPU: same order on any device
        # One gather per epoch; each mini-batch is then a slice (a view), not a gather per tensor.
        shuffled = _rows(columns, order)
        for m in range(ppo.mini_batches):
            start = m * per_mini
            mine = slice(start + rank * per_mini // world_size, start + (rank + 1) * per_mini // world_size)
            whole = {key: shuffled[key][start:start + per_mini] for key in ("advantages", "keep", "step_mask")}
            rows = {key: shuffled[key][mine] for key in row_keys}
            model_args = (_rows(shuffled["obs"], mine), shuffled["actions"][mine],
                          _rows(shuffled["extras"], mine) if "extras" in shuffled else None, True,
                          normalize is not None)
            if stepper is not None:
                _, metrics, grad_norm = stepper.step(model_args, (ppo, rank, world_size, whole, rows))
                metrics.pop(KL_SHARE)
                metrics["train/grad_norm"] = grad_norm.detach()
            else:
                loss, metrics = minibatch_loss(model, ppo, rank, world_size, model_args, whole, rows)
                kl_share = metrics.pop(KL_SHARE)
                if not warmup:
                    _policy_step_rates(optimizer, ppo, factor, kl_share, world_size, parts.policy)
                if anchor is not None and not warmup:
                    extra, extra_metrics = anchor(epoch * ppo.mini_batches + m)
                    loss = loss + extra
                    metrics.update(extra_metrics)
                metrics.update(_eager_step(optimizer, loss, parts, all_reduce_grads))
            # Kept as tensors and combined once after the loop: no per-step conversion to Python floats.
            for key, value in metrics.items():
                step_metrics.setdefault(key, []).append(value)
    return _update_metrics(step_metrics, batch, ppo, optimizer)


@dataclass(frozen=True)
class _GradParts:
    """The trainable parameters, and the same split into the critic's and the rest (the policy's)."""

    params: list
    """Every trainable parameter, in the model's order."""
    critic: list
    policy: list
    max_norm: float
    frozen: tuple = ()
    """Parameters that get no gradient this update (the policy's, during the critic's warm-up)."""


#: :func:`ppo_objective`'s metric (not logged) holding this rank's share of the mini-batch's approximate KL.
KL_SHARE = "approx_kl_share"

#: The adaptive rate's bounds, as multiples of the configured one (``PPOSpec.desired_kl``).
KL_SCALE_BOUNDS = (1e-2, 10.0)
KL_SCALE_FACTOR = 1.5


def _set_rates(optimizer, ppo: PPOSpec, factor: float) -> None:
    """Every group's rate: its own base rate (a faster value head's) x the anneal factor x the
    adaptive scale it carries (``kl_scale``: in the optimizer's state dict, so resume is exact) x
    its warm-up ramp (``ramp``, :func:`_ramp_rates`)."""
    for group in optimizer.param_groups:
        group["lr"] = group.get("base_lr", ppo.lr) * factor * group.get("kl_scale", 1.0) * group.get("ramp", 1.0)


def _policy_step_rates(optimizer, ppo: PPOSpec, factor: float, kl_share: torch.Tensor, world_size: int,
                       policy_params: list) -> None:
    """The rates of a step that trains the policy, set before it: adapted to the mini-batch's KL
    (``desired_kl``, before the step as rsl_rl does) and ramped (``warmup_steps``)."""
    if ppo.desired_kl is not None:
        _adapt_rates(optimizer, ppo, factor, kl_share, world_size)
    if ppo.warmup_steps:
        _ramp_rates(optimizer, ppo, factor, policy_params)


def _ramp_rates(optimizer, ppo: PPOSpec, factor: float, policy_params: list) -> None:
    """Before each of the policy's first ``ppo.warmup_steps`` optimizer steps, set the rate of every
    group holding a policy parameter to (k + 1) / ``warmup_steps`` of its rate, k the steps the policy
    has taken: Adam's first steps move every weight by about the full rate, whatever the gradient's
    size. k is Adam's own step count of the policy's first parameter, so a resumed run (the
    optimizer's state restored) continues the ramp exactly. A value head in a group of its own
    (``value_lr``) is not ramped."""
    if not policy_params:
        return
    step = optimizer.state.get(policy_params[0], {}).get("step", 0)
    ramp = min(1.0, (float(step) + 1.0) / ppo.warmup_steps)
    policy = {id(p) for p in policy_params}
    for group in optimizer.param_groups:
        if any(id(p) in policy for p in group["params"]):
            group["ramp"] = ramp
    _set_rates(optimizer, ppo, factor)


def mini_batch_kl(kl_share: torch.Tensor, world_size: int) -> float:
    """The whole mini-batch's approximate KL from this rank's share of it (:data:`KL_SHARE`: the sum
    over its decisions divided by the mini-batch's count of them): the shares summed over the ranks,
    so every rank gets the 1-rank value however unevenly the counted decisions fall on the ranks
    (action level, GRPO's mask, a mini-batch that does not split evenly). Collective with ranks."""
    kl = kl_share.detach().to(torch.float64).reshape(1)
    if world_size > 1 and torch.distributed.is_initialized():
        torch.distributed.all_reduce(kl)
    return float(kl)


def _adapt_rates(optimizer, ppo: PPOSpec, factor: float, kl_share: torch.Tensor, world_size: int) -> None:
    """rsl_rl's adaptive schedule: divide the rate by 1.5 when the mini-batch's approximate KL to the
    rollout policy is above twice ``desired_kl``, multiply it by 1.5 below half of it (within
    :data:`KL_SCALE_BOUNDS` of the configured rate). Every rank decides on the whole mini-batch's KL
    (:func:`mini_batch_kl`)."""
    kl_value, scale = mini_batch_kl(kl_share, world_size), optimizer.param_groups[0].get("kl_scale", 1.0)
    if kl_value > 2.0 * ppo.desired_kl:
        scale = max(scale / KL_SCALE_FACTOR, KL_SCALE_BOUNDS[0])
    elif kl_value < 0.5 * ppo.desired_kl:
        scale = min(scale * KL_SCALE_FACTOR, KL_SCALE_BOUNDS[1])
    for group in optimizer.param_groups:
        group["kl_scale"] = scale
    _set_rates(optimizer, ppo, factor)


def _full(norm: torch.Tensor) -> torch.Tensor:
    return norm.full_tensor() if hasattr(norm, "full_tensor") else norm  # a sharded model's norm: partial per rank


def _eager_step(optimizer, loss: torch.Tensor, parts: _GradParts, all_reduce_grads: Callable[[], None]) -> dict:
    """Backward, sum over ranks, clip (one norm over the whole model), step; ``parts.frozen`` get no
    gradient, so the optimizer leaves them and their state untouched. Returns the gradient norms
    before clipping: the whole model's and, where it has a critic, the critic parameters' and the
    rest's (``train/grad_norm``, ``..._critic``, ``..._policy``)."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    all_reduce_grads()
    for p in parts.frozen:
        p.grad = None
    metrics = {}
    if parts.critic:
        for name, group in (("critic", parts.critic), ("policy", parts.policy)):
            grads = [p.grad for p in group if p.grad is not None]
            norm = torch.nn.utils.get_total_norm(grads, foreach=True) if grads else torch.zeros(())
            metrics[f"train/grad_norm_{name}"] = _full(norm).detach()
    metrics["train/grad_norm"] = _full(torch.nn.utils.clip_grad_norm_(parts.params, parts.max_norm, foreach=True))
    optimizer.step()
    return metrics


def inner_policy(model):
    """The :class:`Policy` inside a trainer's wrappers (``.policy`` of a ``NormalizedPolicy``,
    ``.module`` of a data-parallel wrapper); ``model`` itself when it wraps none."""
    while not hasattr(model, "critic_modules") and (hasattr(model, "policy") or hasattr(model, "module")):
        model = getattr(model, "policy", None) or model.module
    return model


def joint_chunk_logprob(model) -> bool:
    """Whether the policy in ``model``'s wrappers scores a chunk as one joint likelihood
    (``Policy.joint_chunk_logprob``; :attr:`PPOSpec.joint_chunk`)."""
    return bool(getattr(inner_policy(model), "joint_chunk_logprob", False))


def critic_parameter_ids(model) -> set[int]:
    """``id`` of every parameter under the policy's ``critic_modules`` (``model`` may wrap the
    policy, as ``.policy`` or ``.module``; matched by name, as the critic's learning rate is)."""
    modules = tuple(getattr(inner_policy(model), "critic_modules", ()))
    return {id(p) for name, p in model.named_parameters()
            if any(f".{module}." in f".{name}." for module in modules)}


@torch.no_grad()
def proximal_logprobs(model, batch: dict, rows_per_pass: int) -> torch.Tensor:
    """Log-probs ``[B, C]`` of the batch's actions under ``model``'s current weights (in slices of
    ``rows_per_pass`` rows, so memory stays that of one mini-batch)."""
    size, parts = batch["actions"].shape[0], []
    for start in range(0, size, max(rows_per_pass, 1)):
        rows = slice(start, start + rows_per_pass)
        extras = _rows(batch["extras"], rows) if "extras" in batch else None
        logprobs, _, _ = model(_rows(batch["obs"], rows), batch["actions"][rows], extras, False, False)
        parts.append(logprobs.detach())
    return torch.cat(parts).to(batch["logprobs"].dtype)


_REDUCE = {"mean": torch.mean, "max": torch.amax, "min": torch.amin}


def _update_metrics(step_metrics: dict[str, list[torch.Tensor]], batch: dict, ppo: PPOSpec, optimizer) -> dict:
    """Every step's metrics combined (the mean; the max / min of a ``_max`` / ``_min`` key, see
    :mod:`~infinirl.algorithms.metrics`), plus the update's own (explained variance, lr, steps)."""
    # The rollout-vs-trainer log-prob mismatch is that of the first mini-batch, before any step.
    mismatch = step_metrics.pop("train/logprob_mismatch", [torch.zeros(())])[0]
    metrics = {key: float(_REDUCE[metric_reduction(key)](torch.stack(values).to(torch.float64)))
               for key, values in step_metrics.items()}
    if ppo.critic:
        returns = batch["returns"][:, 0] if ppo.gae_level == "action" else batch["returns"]
        variance = float(returns.var())
        metrics["train/explained_variance"] = (float("nan") if variance == 0
                                               else 1.0 - float((returns - batch["values"]).var()) / variance)
    metrics["train/lr"] = optimizer.param_groups[0]["lr"]
    if ppo.desired_kl is not None:
        metrics["train/kl_scale"] = optimizer.param_groups[0].get("kl_scale", 1.0)
    metrics["train/logprob_mismatch"] = float(mismatch)
    metrics["train/optimizer_steps"] = ppo.epochs * ppo.mini_batches
    return metrics


def ppo_objective(ppo: PPOSpec, rank: int, world_size: int, logprobs: torch.Tensor, entropy: torch.Tensor | None,
                  values: torch.Tensor, whole: dict, mine: dict) -> tuple[torch.Tensor, dict]:
    """This rank's loss on one mini-batch and its detached metrics (tensors).

    ``logprobs`` / ``entropy`` ``[m, C]`` and ``values`` ``[m]`` are the model's outputs on this
    rank's rows; ``mine`` holds the same rows' ``logprobs`` (old), ``values`` (old) and ``returns``;
    ``whole`` holds ``advantages``, ``keep`` and ``step_mask`` of the *whole* mini-batch (all
    ranks), whose statistics and counts every rank shares: advantage normalisation and every
    loss normaliser are mini-batch-global, so the ranks' gradients sum to the 1-rank gradient.

    Among the metrics, :data:`KL_SHARE` is this rank's share of the mini-batch's approximate KL
    (for ``desired_kl``; :func:`ppo_update` takes it out before logging).

    A pure function of tensors (no Python number read back from them, no branch on their values),
    so ``torch.compile`` takes it whole, without graph breaks (``actor.compile``).
    """
    action_level = ppo.gae_level == "action"
    adv, keep = whole["advantages"], whole["keep"]  # [M] chunk level, [M, C] action level
    # executed: the executed actions to train on [M, C]; mask: the rows a decision's log-prob and
    # entropy sum, the executed ones or all of a jointly denoised chunk (joint_chunk: the rows an
    # episode's end left unexecuted were sampled with the rest); weights: the policy-loss rows.
    executed = whole["step_mask"] * (keep if action_level else keep[:, None])
    mask = keep[:, None] * torch.ones_like(executed) if ppo.joint_chunk and not action_level else executed
    weights = mask if action_level else keep
    if ppo.normalize_advantages:  # statistics of the whole mini-batch (all ranks)
        count = weights.sum()
        mean = (adv * weights).sum() / count.clamp(min=1)
        std = torch.sqrt(((adv - mean) ** 2 * weights).sum() / (count - 1).clamp(min=1))
        adv = (adv - mean) / (std + 1e-8)
    n_pg, n_entropy, n_value = weights.sum(), mask.sum(), float(adv.shape[0])
    size = adv.shape[0]
    share = slice(rank * size // world_size, (rank + 1) * size // world_size)
    adv, mask, weights, executed = adv[share], mask[share], weights[share], executed[share]
    old = mine["logprobs"]
    behaviour = mine.get("behaviour_logprobs")
    # Rollout vs trainer on the same actions: against the rollout's own log-probs, which with
    # decoupled PPO are the behaviour ones (``old`` is then the trainer's proximal recomputation).
    rollout = old if behaviour is None else behaviour
    metrics = {"train/logprob_mismatch": masked_mean((logprobs.detach() - rollout).abs(), executed)}
    correction = {} if behaviour is None else {"is_cap": ppo.is_cap, "is_cap_mode": ppo.is_cap_mode}
    if action_level:
        pg = ppo_clip_loss(logprobs=logprobs, old_logprobs=old, advantages=adv, response_mask=weights,
                           clip_low=ppo.clip, behaviour_logprobs=behaviour, **correction)
        returns = mine["returns"][:, 0]
    else:
        pg = ppo_clip_loss(logprobs=(logprobs * mask).sum(-1), old_logprobs=(old * mask).sum(-1),
                           advantages=adv, response_mask=weights, clip_low=ppo.clip,
                           behaviour_logprobs=None if behaviour is None else (behaviour * mask).sum(-1),
                           **correction)
        returns = mine["returns"]
    for key in ("is_weight_mean", "is_capped_fraction", "behaviour_logprob_abs_diff"):
        if key in pg.metrics:
            metrics[f"train/{key}"] = pg.metrics[key]
    loss = pg_loss = aggregate(pg.loss_mat, weights, "token-mean", n_pg)
    metrics.update({"train/policy_loss": pg_loss.detach(), "train/approx_kl": pg.metrics["approx_kl"],
                    "train/clip_fraction": pg.metrics["clip_fraction"],
                    # approx_kl is this rank's mean; its sum over the mini-batch's count adds up over ranks
                    KL_SHARE: pg.metrics["approx_kl"] * weights.sum() / n_pg.clamp(min=1)})
    if ppo.critic:
        ones = torch.ones_like(returns)
        vl = value_loss(values=values, old_values=mine["values"], returns=returns.to(values.dtype),
                        response_mask=ones, clip_range=ppo.value_clip)
        loss = pg_loss + ppo.value_coef * aggregate(vl.loss_mat, ones, "token-mean", n_value)
        metrics["train/value_loss"] = vl.metrics["value_mse"] / 2
    if entropy is not None:
        ent = entropy_loss(mask, entropy=entropy)
        metrics["train/entropy"] = ent.metrics["entropy"]
        if ppo.entropy_coef:
            loss = loss + ppo.entropy_coef * aggregate(ent.loss_mat, mask, "token-mean", n_entropy)
    return loss, metrics


def ppo_minibatch_loss(model, ppo: PPOSpec, rank: int, world_size: int, model_args: tuple, whole: dict,
                       mine: dict) -> tuple[torch.Tensor, dict]:
    """The policy's forward pass on this rank's rows of a mini-batch (``model_args``: observations,
    actions, extras, with_entropy, obs_normalized), then :func:`ppo_objective`."""
    return ppo_objective_of_outputs(*model(*model_args), ppo, rank, world_size, whole, mine)


def ppo_objective_of_outputs(logprobs, entropy, values, ppo: PPOSpec, rank: int, world_size: int, whole: dict,
                             mine: dict) -> tuple[torch.Tensor, dict]:
    """:func:`ppo_objective` with the model's outputs first (the compiled whole step's objective contract)."""
    return ppo_objective(ppo, rank, world_size, logprobs, entropy, values, whole, mine)


@functools.cache
def compiled_minibatch_loss(compile_: bool):
    """:func:`ppo_minibatch_loss`, compiled once per process when ``actor.compile`` asks for it
    (where the whole step cannot be compiled, e.g. under FSDP2).

    Why: a small policy's mini-batch step is hundreds of tiny ops, each paying the eager
    per-op (and autograd-node) overhead; on CPU that overhead, not arithmetic, is most of the
    update. Compiled, the forward pass and the loss and their backward become a few fused kernels.
    ``dynamic=False``: mini-batch shapes never change within a run. The optimizer step and gradient
    clipping stay eager (already fused / foreach kernels).
    """
    if not compile_:
        return ppo_minibatch_loss
    return torch.compile(ppo_minibatch_loss, dynamic=False)
