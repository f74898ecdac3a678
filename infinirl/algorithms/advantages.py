"""Advantage estimators for LLM rollouts, in the aligned token layout.

Calling convention (the same for every entry of ``ADVANTAGES``, token or embodied)::

    out = ADVANTAGES.get(name)(inputs, **hyperparameters)  # = compute_advantages(name, inputs, ...)
    out.advantages, out.returns, out.mask

``inputs`` is a frozen dataclass holding the *data* (``TokenAdvantageInputs`` here,
``EnvAdvantageInputs`` in ``embodied.py``); keyword arguments hold the *hyperparameters* (gamma,
lambda, eps, ...), each with the default of the paper that introduced it. An estimator reads the
fields it needs and fails with a clear error if one is missing, so a runner can fill every field it
has and switch estimators by name alone.

Advantages are computed once over the whole rollout batch, before it is split into mini-/micro-
batches: batch-level statistics (group means, REINFORCE++ whitening) therefore do not depend on how
the trainer later splits the data.

Token estimators place the sequence reward ``rewards[i]`` on the last generated token of row ``i``
(``response_mask`` decides which tokens are generated) and add optional dense ``token_rewards``
(e.g. a KL penalty from ``kl.kl_penalty``) on every generated token. Outputs are ``[B, L]``, zero
outside ``response_mask``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from infinirl.algorithms.groups import group_index, group_stats
from infinirl.algorithms.masking import (
    as_weight,
    last_valid_index,
    masked_whiten,
    reverse_discounted_scan,
)
from infinirl.algorithms.registry import ADVANTAGES

__all__ = [
    "AdvantageOutput",
    "TokenAdvantageInputs",
    "compute_advantages",
    "dr_grpo",
    "gae",
    "grpo",
    "reinforce_pp",
    "reinforce_pp_baseline",
    "rloo",
]


@dataclass(frozen=True)
class TokenAdvantageInputs:
    """The data a token-level estimator reads. Shapes: ``B`` sequences, ``L`` aligned positions.

    Attributes:
        rewards: ``[B]`` one scalar reward per sequence (verifier or reward-model score).
        response_mask: ``[B, L]`` 1 on generated tokens (``infinirl.data.batch.RESPONSE_MASK``).
        values: ``[B, L]`` critic values, aligned like log-probs: ``values[:, t]`` estimates the
            return from the state *before* token ``t`` is generated. Needed by ``gae`` only.
        token_rewards: ``[B, L]`` optional dense per-token reward added on generated tokens, e.g.
            ``-beta * KL`` from :func:`infinirl.algorithms.kl.kl_penalty`.
        group_size: consecutive samples that share a prompt (group estimators).
        group_ids: ``[B]`` explicit group label per sample; use instead of ``group_size``.
    """

    rewards: torch.Tensor
    response_mask: torch.Tensor
    values: torch.Tensor | None = None
    token_rewards: torch.Tensor | None = None
    group_size: int | None = None
    group_ids: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.response_mask.dim() != 2:
            raise ValueError(f"response_mask must be [B, L], got {tuple(self.response_mask.shape)}")
        batch = self.response_mask.shape[0]
        if self.rewards.shape != (batch,):
            raise ValueError(
                f"rewards must be [B]=({batch},), one scalar per sequence; "
                f"got {tuple(self.rewards.shape)}"
            )
        for name in ("values", "token_rewards"):
            tensor = getattr(self, name)
            if tensor is not None and tensor.shape != self.response_mask.shape:
                raise ValueError(
                    f"{name} must be aligned with response_mask {tuple(self.response_mask.shape)}, "
                    f"got {tuple(tensor.shape)}"
                )

    def group_index(self) -> tuple[torch.Tensor, int]:
        """Dense group number per sample and the number of groups (see ``groups.group_index``)."""
        return group_index(
            self.rewards.shape[0],
            group_size=self.group_size,
            group_ids=self.group_ids,
            device=self.rewards.device,
        )


@dataclass(frozen=True)
class AdvantageOutput:
    """What every estimator returns.

    Attributes:
        advantages: the policy-gradient weights, shaped like the inputs, 0 where ``mask`` is 0.
        returns: the return estimate the advantage was derived from: the lambda-return (critic
            target) for GAE, the discounted reward-to-go for REINFORCE++, the sequence (or episode)
            reward broadcast over its steps for group estimators.
        mask: where ``advantages`` are meaningful (the loss mask to use with them).
    """

    advantages: torch.Tensor
    returns: torch.Tensor
    mask: torch.Tensor


def compute_advantages(name: str, inputs: object, **hyperparameters: float) -> AdvantageOutput:
    """Look up estimator ``name`` in ``ADVANTAGES`` and apply it."""
    return ADVANTAGES.get(name)(inputs, **hyperparameters)


def _require_token_inputs(inputs: object, estimator: str) -> TokenAdvantageInputs:
    if not isinstance(inputs, TokenAdvantageInputs):
        raise TypeError(
            f"advantage estimator {estimator!r} works on token batches: pass TokenAdvantageInputs, "
            f"got {type(inputs).__name__}"
        )
    return inputs


def _float_rewards(inputs: TokenAdvantageInputs) -> torch.Tensor:
    """Sequence rewards as floats (verifiers often return 0/1 integers)."""
    rewards = inputs.rewards
    return rewards if rewards.is_floating_point() else rewards.to(torch.get_default_dtype())


def _dense_rewards(inputs: TokenAdvantageInputs, sequence_rewards: torch.Tensor) -> torch.Tensor:
    """``[B, L]`` rewards: the sequence reward on the last generated token, plus token rewards."""
    mask = inputs.response_mask
    dense = torch.zeros(mask.shape, dtype=sequence_rewards.dtype, device=sequence_rewards.device)
    last = last_valid_index(mask)
    rows = torch.nonzero(last >= 0).squeeze(1)
    dense[rows, last[rows]] = sequence_rewards[rows]
    if inputs.token_rewards is not None:
        dense = dense + inputs.token_rewards.to(dense.dtype) * as_weight(mask, dense)
    return dense


def _broadcast(per_sequence: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return per_sequence[:, None] * as_weight(mask, per_sequence[:, None].expand(mask.shape))


@ADVANTAGES.register("gae")
def gae(inputs: TokenAdvantageInputs, *, gamma: float = 1.0, lam: float = 0.95) -> AdvantageOutput:
    """PPO with a critic: GAE over generated tokens (Schulman et al. 2016, eq. 16).

    ``returns = advantages + values`` are the critic's regression targets (lambda-returns). The
    LLM defaults ``gamma=1`` (the reward is terminal; sequences are short relative to any horizon)
    and ``lam=0.95`` follow Ouyang et al. 2022 / OpenRLHF.
    """
    inputs = _require_token_inputs(inputs, "gae")
    if inputs.values is None:
        raise ValueError(
            "advantage estimator 'gae' needs critic values (TokenAdvantageInputs.values)"
        )
    rewards = _dense_rewards(inputs, _float_rewards(inputs).to(inputs.values.dtype))
    weight = as_weight(inputs.response_mask, rewards)
    advantages = reverse_discounted_scan(rewards, inputs.values, weight, gamma, lam)
    returns = (advantages + inputs.values) * weight
    return AdvantageOutput(advantages=advantages, returns=returns, mask=inputs.response_mask)


@ADVANTAGES.register("grpo")
def grpo(
    inputs: TokenAdvantageInputs, *, eps: float = 1e-6, norm_by_std: bool = True
) -> AdvantageOutput:
    """GRPO: ``A_i = (r_i - mean_g) / (std_g + eps)`` on every token of sample ``i`` (Shao et al.
    2024, DeepSeekMath, section 4.1.2). ``std_g`` is the unbiased group std; a group whose rewards
    are all equal gets advantage exactly 0 (it carries no learning signal).

    ``norm_by_std=False`` gives Dr.GRPO (Liu et al. 2025, "Understanding R1-Zero-Like Training"),
    which drops the std division because it over-weights questions that are too easy or too hard.
    """
    inputs = _require_token_inputs(inputs, "grpo")
    rewards = _float_rewards(inputs)
    index, num_groups = inputs.group_index()
    stats = group_stats(rewards, index, num_groups)
    centred = rewards - stats.mean
    scores = centred / (stats.std + eps) if norm_by_std else centred
    return AdvantageOutput(
        advantages=_broadcast(scores, inputs.response_mask),
        returns=_broadcast(rewards, inputs.response_mask),
        mask=inputs.response_mask,
    )


@ADVANTAGES.register("dr_grpo")
def dr_grpo(inputs: TokenAdvantageInputs) -> AdvantageOutput:
    """Dr.GRPO advantages: group-mean baseline, no std normalisation (``grpo(norm_by_std=False)``).
    Pair it with the ``seq-mean-token-sum-norm`` aggregation to remove the length bias too."""
    return grpo(inputs, norm_by_std=False)


@ADVANTAGES.register("rloo")
def rloo(inputs: TokenAdvantageInputs) -> AdvantageOutput:
    """RLOO: ``A_i = r_i - mean_{j != i} r_j`` over the other samples of the group (Ahmadian et al.
    2024, "Back to Basics", eq. 6; Kool et al. 2019). A group of one has no baseline: advantage 0.
    """
    inputs = _require_token_inputs(inputs, "rloo")
    rewards = _float_rewards(inputs)
    index, num_groups = inputs.group_index()
    stats = group_stats(rewards, index, num_groups)
    # r_i - (n mean - r_i) / (n - 1) = n / (n - 1) * (r_i - mean): exactly 0 for a constant group
    others = stats.count - 1
    scores = stats.count / others.clamp(min=1.0) * (rewards - stats.mean)
    return AdvantageOutput(
        advantages=_broadcast(scores, inputs.response_mask),
        returns=_broadcast(rewards, inputs.response_mask),
        mask=inputs.response_mask,
    )


def _reinforce_pp_from(
    inputs: TokenAdvantageInputs, sequence_rewards: torch.Tensor, gamma: float, eps: float
) -> AdvantageOutput:
    rewards = _dense_rewards(inputs, sequence_rewards)
    weight = as_weight(inputs.response_mask, rewards)
    returns = reverse_discounted_scan(rewards, torch.zeros_like(rewards), weight, gamma, 1.0)
    advantages = masked_whiten(returns, weight, eps)
    return AdvantageOutput(advantages=advantages, returns=returns, mask=inputs.response_mask)


@ADVANTAGES.register("reinforce_pp")
def reinforce_pp(
    inputs: TokenAdvantageInputs, *, gamma: float = 1.0, eps: float = 1e-8
) -> AdvantageOutput:
    """REINFORCE++ (Hu 2025, arXiv 2501.03262): discounted token reward-to-go
    ``G_t = sum_{k>=t} gamma^(k-t) r_k`` (sequence reward on the last token plus optional per-token
    KL penalty), then whitened over *all* valid tokens of the batch (global advantage
    normalisation replaces the critic's and the group's baseline)."""
    inputs = _require_token_inputs(inputs, "reinforce_pp")
    return _reinforce_pp_from(inputs, _float_rewards(inputs), gamma, eps)


@ADVANTAGES.register("reinforce_pp_baseline")
def reinforce_pp_baseline(
    inputs: TokenAdvantageInputs, *, gamma: float = 1.0, eps: float = 1e-8
) -> AdvantageOutput:
    """REINFORCE++-baseline (Hu 2025, section 3.2): subtract the group mean from each sequence
    reward first (a per-prompt baseline, robust to reward scale across prompts), then proceed as
    ``reinforce_pp``: discounted token returns and global whitening."""
    inputs = _require_token_inputs(inputs, "reinforce_pp_baseline")
    index, num_groups = inputs.group_index()
    rewards = _float_rewards(inputs)
    centred = rewards - group_stats(rewards, index, num_groups).mean
    return _reinforce_pp_from(inputs, centred, gamma, eps)
