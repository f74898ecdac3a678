"""Advantage estimators for vectorised environment rollouts (embodied RL).

Layout: ``[T, N]`` (rollout step, env) or ``[T, N, C]`` when the policy emits a *chunk* of ``C``
actions per step (VLAs such as OpenVLA-OFT or pi0 execute action chunks) and the env reports one
reward per executed action. Same calling convention as ``advantages.py``:
``ADVANTAGES.get("embodied_gae")(EnvAdvantageInputs(...), gamma=..., lam=..., level=...)``.

Episode ends. Vectorised envs auto-reset, so step ``t+1`` after a done belongs to a new episode.
An episode can end in two ways that must be treated differently (Pardo et al. 2018, "Time Limits
in Reinforcement Learning"):

* **termination** (success, failure): the true future return is 0, no bootstrap;
* **truncation** (time limit): the task would have gone on, so bootstrap with the value of the
  *final* observation, ``V(final_obs)``, which the env returns alongside the reset observation.

``dones`` marks both; ``truncations`` marks the subset that are time limits, and ``final_values``
carries ``V(final_obs)`` there. In both cases the GAE chain is cut: the next step's advantage
belongs to another episode.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import torch

from infinirl.algorithms.advantages import AdvantageOutput
from infinirl.algorithms.groups import group_index, group_stats
from infinirl.algorithms.registry import ADVANTAGES

__all__ = ["EnvAdvantageInputs", "embodied_gae", "embodied_grpo", "normalize_per_task"]


@dataclass(frozen=True)
class EnvAdvantageInputs:
    """The data an embodied estimator reads (``T`` steps, ``N`` envs, optional chunk of ``C``).

    Attributes:
        rewards: ``[T, N]`` per step, or ``[T, N, C]`` per action of each executed chunk.
        dones: ``[T, N]`` or ``[T, N, C]`` bool: the episode ended with this step (either way).
            ``[T, N]`` with ``[T, N, C]`` rewards means "ended after the chunk's last action".
        values: critic values of each step's observation: ``[T, N]`` for chunk-level GAE;
            ``[T, N, C]`` (one per action) or ``[T, N]`` (one per chunk, a critic that sees only
            the chunk's first observation) for action-level GAE. Needed by ``embodied_gae``.
        bootstrap_values: ``[N]`` value of the observation after the last step, ``V(s_T)``.
            Needed by ``embodied_gae`` (it is ignored where the last step ended an episode).
        truncations: like ``dones``; the dones caused by a time limit (default: none).
        final_values: like ``dones``; ``V(final_obs)`` where ``truncations`` is set (other entries
            are ignored). Needed whenever any truncation is set.
        group_size: consecutive envs that share a reset state (``embodied_grpo``).
        group_ids: ``[N]`` explicit group label per env; use instead of ``group_size``.
    """

    rewards: torch.Tensor
    dones: torch.Tensor
    values: torch.Tensor | None = None
    bootstrap_values: torch.Tensor | None = None
    truncations: torch.Tensor | None = None
    final_values: torch.Tensor | None = None
    group_size: int | None = None
    group_ids: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.rewards.dim() not in (2, 3):
            raise ValueError(
                f"rewards must be [T, N] or [T, N, C], got {tuple(self.rewards.shape)}"
            )
        steps_envs = tuple(self.rewards.shape[:2])
        for name in ("dones", "truncations", "final_values", "values"):
            tensor = getattr(self, name)
            if tensor is None:
                continue
            if tuple(tensor.shape[:2]) != steps_envs or tensor.dim() not in (2, self.rewards.dim()):
                raise ValueError(
                    f"{name} must be [T, N]={steps_envs} or shaped like rewards "
                    f"{tuple(self.rewards.shape)}; got {tuple(tensor.shape)}"
                )
        for name in ("truncations", "final_values"):
            tensor = getattr(self, name)
            if tensor is not None and tensor.shape != self.dones.shape:
                raise ValueError(
                    f"{name} must be shaped like dones {tuple(self.dones.shape)}, "
                    f"got {tuple(tensor.shape)}"
                )
        if self.bootstrap_values is not None and self.bootstrap_values.shape != steps_envs[1:]:
            raise ValueError(
                f"bootstrap_values must be [N]=({steps_envs[1]},), got "
                f"{tuple(self.bootstrap_values.shape)}"
            )

    @property
    def chunk_size(self) -> int | None:
        """``C`` when rewards are per action of a chunk, else None."""
        return self.rewards.shape[2] if self.rewards.dim() == 3 else None


# --- flattening the chunk dimension ------------------------------------------------------------


def _flatten_actions(tensor: torch.Tensor, chunk: int, *, end_of_chunk: bool) -> torch.Tensor:
    """``[T, N, C]`` -> ``[T*C, N]`` in execution order; a ``[T, N]`` flag is first placed on the
    chunk's last action (``end_of_chunk``) or repeated over the chunk."""
    if tensor.dim() == 2:
        if end_of_chunk:
            expanded = torch.zeros(*tensor.shape, chunk, dtype=tensor.dtype, device=tensor.device)
            expanded[..., -1] = tensor
            tensor = expanded
        else:
            tensor = tensor[..., None].expand(*tensor.shape, chunk)
    steps, envs, _ = tensor.shape
    return tensor.permute(0, 2, 1).reshape(steps * chunk, envs)


def _unflatten_actions(tensor: torch.Tensor, chunk: int) -> torch.Tensor:
    """Inverse of :func:`_flatten_actions`: ``[T*C, N]`` -> ``[T, N, C]``."""
    steps_times_chunk, envs = tensor.shape
    return tensor.reshape(steps_times_chunk // chunk, chunk, envs).permute(0, 2, 1)


def _identity(tensor: torch.Tensor) -> torch.Tensor:
    return tensor


def _reduce_chunk(tensor: torch.Tensor | None, how: Callable) -> torch.Tensor | None:
    return how(tensor) if tensor is not None and tensor.dim() == 3 else tensor


@dataclass(frozen=True)
class _TimeSeries:
    """Per-decision ``[S, N]`` tensors after choosing the GAE level, plus the way back."""

    rewards: torch.Tensor
    values: torch.Tensor
    dones: torch.Tensor
    truncations: torch.Tensor
    final_values: torch.Tensor
    restore: Callable[[torch.Tensor], torch.Tensor]
    shares_value: torch.Tensor | None = None
    """``[S, N]`` bool: the step's successor lies in the same chunk and has the same (chunk) value,
    so GAE does not bootstrap there (lambda 1): the chunk's actions see ``V`` of the next chunk."""


def _chunk_level(inputs: EnvAdvantageInputs) -> _TimeSeries:
    """One decision per chunk: rewards summed over the chunk's actions (undiscounted within the
    chunk, as RLinf's ``chunk_level`` reward), an episode end anywhere in the chunk ends it."""
    if inputs.values.dim() != 2:
        raise ValueError(f"chunk-level GAE needs values [T, N], got {tuple(inputs.values.shape)}")
    if inputs.final_values is not None and inputs.final_values.dim() != 2:
        raise ValueError("chunk-level GAE needs final_values [T, N]: one V(final obs) per chunk")
    dones = _reduce_chunk(inputs.dones.bool(), lambda t: t.any(dim=-1))
    truncations = _reduce_chunk(_truncations(inputs), lambda t: t.any(dim=-1))
    final_values = _final_values(inputs, like=inputs.values)
    rewards = _reduce_chunk(inputs.rewards, lambda t: t.sum(dim=-1))
    return _TimeSeries(rewards, inputs.values, dones, truncations, final_values, _identity)


def _action_level(inputs: EnvAdvantageInputs) -> _TimeSeries:
    """One decision per executed action: the chunk is unrolled into ``C`` consecutive steps with
    per-action rewards, so credit is assigned inside the chunk.

    With one value per chunk (``[T, N]``), every action of a chunk has the chunk's value as its
    baseline, and inside the chunk the return runs on undiscounted by lambda to the next chunk's
    value (``shares_value``): bootstrapping each action from the value it shares with its
    successor would give ``r + (gamma - 1) V`` terms that do not telescope, so value would barely
    pass from one chunk to the next and a perfect critic would not give zero advantages."""
    chunk = inputs.chunk_size
    if chunk is None:
        raise ValueError(
            "action-level GAE needs per-action rewards shaped [T, N, C]; got rewards "
            f"{tuple(inputs.rewards.shape)}, values {tuple(inputs.values.shape)}"
        )
    shares_value = None
    if inputs.values.dim() == 2:
        inside = torch.ones(*inputs.values.shape, chunk, dtype=torch.bool, device=inputs.values.device)
        inside[..., -1] = False
        shares_value = _flatten_actions(inside, chunk, end_of_chunk=False)
    return _TimeSeries(
        rewards=_flatten_actions(inputs.rewards, chunk, end_of_chunk=False),
        values=_flatten_actions(inputs.values, chunk, end_of_chunk=False),
        dones=_flatten_actions(inputs.dones.bool(), chunk, end_of_chunk=True),
        truncations=_flatten_actions(_truncations(inputs), chunk, end_of_chunk=True),
        final_values=_flatten_actions(
            _final_values(inputs, like=inputs.dones.to(inputs.values.dtype)),
            chunk,
            end_of_chunk=True,
        ),
        restore=partial(_unflatten_actions, chunk=chunk),
        shares_value=shares_value,
    )


_GAE_LEVELS: dict[str, Callable[[EnvAdvantageInputs], _TimeSeries]] = {
    "chunk": _chunk_level,
    "action": _action_level,
}


def _truncations(inputs: EnvAdvantageInputs) -> torch.Tensor:
    if inputs.truncations is None:
        return torch.zeros_like(inputs.dones, dtype=torch.bool)
    return inputs.truncations.bool()


def _final_values(inputs: EnvAdvantageInputs, like: torch.Tensor) -> torch.Tensor:
    """``final_values``, or zeros shaped ``like`` when no episode was truncated."""
    if inputs.final_values is not None:
        return inputs.final_values
    if inputs.truncations is not None and inputs.truncations.bool().any():
        raise ValueError(
            "truncated episodes must bootstrap from V(final observation): pass "
            "EnvAdvantageInputs.final_values (or drop truncations to treat them as terminations)"
        )
    return torch.zeros_like(like)


@ADVANTAGES.register("embodied_gae")
def embodied_gae(
    inputs: EnvAdvantageInputs, *, gamma: float = 0.99, lam: float = 0.95, level: str = "chunk"
) -> AdvantageOutput:
    """GAE over env steps with auto-reset, bootstrapping truncated episodes and not terminated ones.

    For each decision ``s``: the successor value is ``V_{s+1}`` (``bootstrap_values`` after the
    last one); if the episode ended at ``s`` it is ``final_values_s`` for a truncation and 0 for a
    termination. ``delta_s = r_s + gamma * next_value_s - V_s`` and
    ``A_s = delta_s + gamma * lam * (1 - done_s) * A_{s+1}`` (Schulman et al. 2016, eq. 16);
    ``returns = A + V``. ``level`` is ``"chunk"`` (one decision per action chunk, outputs
    ``[T, N]``) or ``"action"`` (one per executed action, outputs ``[T, N, C]``), after RLinf's
    ``chunk_level`` / ``action_level`` reward types.
    """
    if not isinstance(inputs, EnvAdvantageInputs):
        raise TypeError(f"embodied_gae needs EnvAdvantageInputs, got {type(inputs).__name__}")
    if inputs.values is None or inputs.bootstrap_values is None:
        raise ValueError("embodied_gae needs values and bootstrap_values (V of the last obs)")
    if level not in _GAE_LEVELS:
        raise ValueError(f"unknown GAE level {level!r}; choose one of {sorted(_GAE_LEVELS)}")
    series = _GAE_LEVELS[level](inputs)
    values = series.values
    dones = series.dones | series.truncations
    successor = torch.cat([values[1:], inputs.bootstrap_values[None].to(values.dtype)], dim=0)
    successor = torch.where(series.truncations, series.final_values.to(values.dtype), successor)
    successor = torch.where(dones & ~series.truncations, torch.zeros_like(successor), successor)
    deltas = series.rewards.to(values.dtype) + gamma * successor - values
    continues = (~dones).to(values.dtype)
    trace = torch.full_like(values, lam)
    if series.shares_value is not None:
        trace = torch.where(series.shares_value, torch.ones_like(trace), trace)
    advantages = torch.zeros_like(values)
    running = torch.zeros_like(values[0])
    for step in range(values.shape[0] - 1, -1, -1):
        running = deltas[step] + gamma * trace[step] * continues[step] * running
        advantages[step] = running
    advantages = series.restore(advantages)
    returns = advantages + series.restore(values)
    return AdvantageOutput(advantages, returns, torch.ones_like(advantages, dtype=torch.bool))


@ADVANTAGES.register("embodied_grpo")
def embodied_grpo(
    inputs: EnvAdvantageInputs, *, eps: float = 1e-6, norm_by_std: bool = True, baseline: bool = True,
    per_episode: bool = False,
) -> AdvantageOutput:
    """Embodied GRPO: each env's *first* episode return, group-normalised across envs that were
    reset to the same state (same task and seed), broadcast to every step of that episode.

    The return sums the rewards from step 0 through the first done (the whole rollout if the
    episode has not ended). Steps after the first done belong to an episode that started from a
    different state, so they are outside ``mask`` and get advantage 0 (as RLinf does). Normalisation
    is ``(R - mean_g) / (std_g + eps)`` with the unbiased group std, or only the mean with
    ``norm_by_std=False``; ``baseline=False`` keeps the raw return ``R`` (REINFORCE without a
    baseline: with a 0/1 success reward only successful episodes get a gradient, and no chunk is
    pushed away). ``per_episode=True`` scales each env's advantages by the mean first-episode
    length over its own, so that every episode weighs the same in a loss averaged over decisions
    (short solved episodes as much as long ones). Outputs are shaped like ``rewards``.
    """
    if not baseline and norm_by_std:
        raise ValueError("embodied_grpo: baseline=False keeps the raw returns; it needs norm_by_std=False")
    if not isinstance(inputs, EnvAdvantageInputs):
        raise TypeError(f"embodied_grpo needs EnvAdvantageInputs, got {type(inputs).__name__}")
    chunk = inputs.chunk_size
    episode_ends = inputs.dones.bool() | _truncations(inputs)
    if chunk is None:
        rewards, dones, restore = inputs.rewards, episode_ends, _identity
    else:
        rewards = _flatten_actions(inputs.rewards, chunk, end_of_chunk=False)
        dones = _flatten_actions(episode_ends, chunk, end_of_chunk=True)
        restore = partial(_unflatten_actions, chunk=chunk)
    rewards = rewards if rewards.is_floating_point() else rewards.to(torch.get_default_dtype())
    ended_before = (torch.cumsum(dones.long(), dim=0) - dones.long()) > 0
    first_episode = ~ended_before
    episode_return = (rewards * first_episode).sum(dim=0)
    index, num_groups = group_index(
        episode_return.shape[0],
        group_size=inputs.group_size,
        group_ids=inputs.group_ids,
        device=episode_return.device,
    )
    stats = group_stats(episode_return, index, num_groups)
    centred = episode_return - stats.mean if baseline else episode_return
    scores = centred / (stats.std + eps) if norm_by_std else centred
    weight = first_episode.to(rewards.dtype)
    if per_episode:
        lengths = weight.sum(dim=0)
        scores = scores * lengths.mean() / lengths.clamp_min(1.0)
    return AdvantageOutput(
        advantages=restore(scores[None] * weight),
        returns=restore(episode_return[None] * weight),
        mask=restore(first_episode),
    )


def normalize_per_task(advantages: torch.Tensor, env_tasks: torch.Tensor, mask: torch.Tensor | None = None,
                       eps: float = 1e-8) -> torch.Tensor:
    """Advantages ``[T, N]`` or ``[T, N, C]`` shifted and scaled to mean 0 and std 1 (Bessel)
    within each task: env ``n`` runs task ``env_tasks[n]``; statistics over the entries inside
    ``mask`` (all if None); entries outside it are returned unchanged.

    Why: on a multi-task env one policy's update weighs the tasks by the scale of their
    advantages, which follows the scale of their shaped rewards, not how much there is to gain;
    a task whose returns vary little (or whose critic fits well) then hardly moves the policy.
    Normalised per task, every task's decisions pull with the same overall strength (the
    multi-task normalisation PopArt motivates, Hessel et al. 2019)."""
    if env_tasks.shape != (advantages.shape[1],):
        raise ValueError(f"env_tasks must be [N]=({advantages.shape[1]},), one task per env column; "
                         f"got {tuple(env_tasks.shape)}")
    if mask is None:
        mask = torch.ones_like(advantages, dtype=torch.bool)
    if mask.shape != advantages.shape:
        raise ValueError(f"mask must have the advantages' shape {tuple(advantages.shape)}, got {tuple(mask.shape)}")
    labels = env_tasks.to(advantages.device).reshape(1, -1, *([1] * (advantages.dim() - 2))).expand_as(advantages)
    inside = mask.to(torch.bool)
    wide = advantages.to(torch.float64)
    out = wide.clone()
    for task in torch.unique(env_tasks).tolist():
        cells = inside & (labels == task)
        values = wide[cells]
        if values.numel() == 0:
            continue
        std = values.std() if values.numel() > 1 else values.new_zeros(())
        out[cells] = (values - values.mean()) / (std + eps)
    return out.to(advantages.dtype)
