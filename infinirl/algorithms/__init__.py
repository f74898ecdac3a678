"""RL algorithms as pure tensor functions, chosen by name through registries. Imports only torch.

Modules, one job each:

* ``registry``     the generic ``Registry`` and the four algorithm registries;
* ``advantages``   token-level estimators (gae, grpo, dr_grpo, rloo, reinforce_pp[_baseline]);
* ``embodied``     env-rollout estimators (embodied_gae at chunk/action level, embodied_grpo,
                   normalize_per_task);
* ``embodied_ppo`` the embodied PPO objective and its epochs of mini-batch steps (PPO, embodied GRPO);
* ``losses``       PPO clip (clip-higher, dual clip, TIS / decoupled PPO), value and entropy losses;
* ``kl``           k1/k2/k3 KL estimators as a loss term or a per-token reward penalty;
* ``aggregation``  loss matrix -> scalar with a mini-batch-global normaliser (split-invariant);
* ``filters``      DAPO dynamic sampling and overlong reward shaping;
* ``sac``, ``imitation``  off-policy (SAC) and imitation (BC / DAgger) losses;
* ``masking``, ``groups``  masked statistics and prompt-group bookkeeping shared by the above;
* ``metrics``      combining logged metrics over micro-batches, ranks and steps (``_max`` / ``_min`` keys
                   by max / min, the rest by mean).

Importing this package registers every built-in entry.
"""

from infinirl.algorithms.advantages import (
    AdvantageOutput,
    TokenAdvantageInputs,
    compute_advantages,
    dr_grpo,
    gae,
    grpo,
    reinforce_pp,
    reinforce_pp_baseline,
    rloo,
)
from infinirl.algorithms.aggregation import (
    AggregationMode,
    aggregate,
    aggregate_locally,
    aggregation_normaliser,
)
from infinirl.algorithms.embodied import EnvAdvantageInputs, embodied_gae, embodied_grpo, normalize_per_task
from infinirl.algorithms.embodied_ppo import PPOSpec, ppo_objective
from infinirl.algorithms.filters import (
    DynamicSamplingBuffer,
    DynamicSamplingResult,
    group_is_informative,
    overlong_penalty,
)
from infinirl.algorithms.groups import group_index, group_stats
from infinirl.algorithms.imitation import bc_mse_loss, bc_nll_loss
from infinirl.algorithms.kl import k1, k2, k3, kl_loss, kl_penalty
from infinirl.algorithms.losses import (
    LossOutput,
    behaviour_importance_weight,
    entropy_from_logits,
    entropy_loss,
    policy_gradient_loss,
    ppo_clip_loss,
    truncated_importance_weight,
    value_loss,
)
from infinirl.algorithms.masking import explained_variance, masked_mean, masked_whiten, zero_outside
from infinirl.algorithms.registry import (
    ADVANTAGES,
    AGGREGATIONS,
    KL_ESTIMATORS,
    POLICY_LOSSES,
    Registry,
    UnknownNameError,
)
from infinirl.algorithms.sac import (
    SACLoss,
    sac_actor_loss,
    sac_critic_loss,
    sac_temperature_loss,
    soft_q_target,
)

__all__ = [
    "ADVANTAGES",
    "AGGREGATIONS",
    "KL_ESTIMATORS",
    "POLICY_LOSSES",
    "AdvantageOutput",
    "AggregationMode",
    "DynamicSamplingBuffer",
    "DynamicSamplingResult",
    "EnvAdvantageInputs",
    "LossOutput",
    "PPOSpec",
    "Registry",
    "SACLoss",
    "TokenAdvantageInputs",
    "UnknownNameError",
    "aggregate",
    "aggregate_locally",
    "aggregation_normaliser",
    "bc_mse_loss",
    "bc_nll_loss",
    "behaviour_importance_weight",
    "compute_advantages",
    "dr_grpo",
    "embodied_gae",
    "embodied_grpo",
    "normalize_per_task",
    "entropy_from_logits",
    "entropy_loss",
    "explained_variance",
    "gae",
    "group_index",
    "group_is_informative",
    "group_stats",
    "grpo",
    "k1",
    "k2",
    "k3",
    "kl_loss",
    "kl_penalty",
    "masked_mean",
    "masked_whiten",
    "overlong_penalty",
    "policy_gradient_loss",
    "ppo_objective",
    "ppo_clip_loss",
    "reinforce_pp",
    "reinforce_pp_baseline",
    "rloo",
    "sac_actor_loss",
    "sac_critic_loss",
    "sac_temperature_loss",
    "soft_q_target",
    "truncated_importance_weight",
    "value_loss",
    "zero_outside",
]
