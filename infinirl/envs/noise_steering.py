"""A frozen flow VLA folded into the environment, so that the agent's action is the VLA's initial noise.

``vla_noise:<family>:<task>`` (e.g. ``vla_noise:metaworld:door-open-v3``) wraps every sub-env of
``<family>:<task>``: its observation is the frozen VLA's features of the wrapped env's observation
(``features``: the mean of the VLM's prefix hidden states and the normalised state, as the steered
policies of :mod:`infinirl.models.vla.steered` compute them), its action is the initial noise ``x_0``
of the VLA's deterministic (Euler) sampler, flattened (``chunk_size * max_action_dim`` numbers in
``[-noise_bound, noise_bound]``), and one step decodes that noise into the VLA's action chunk and
runs its first ``chunk`` actions in the wrapped env (rewards summed; stopped where the episode ends).

This is DSRL's own framing (Wagenmaker et al. 2025, "Steering Your Diffusion Policy with Latent
Space Reinforcement Learning"): the diffusion policy becomes part of the environment, so any RL
algorithm over a flat continuous action drives it, in particular off-policy SAC with a replay
buffer and many updates per sample (``infinirl train sac_vla_metaworld``). Every action the
agent takes is one the cloned VLA can produce; RL chooses among them.

Options (besides the wrapped family's, passed on): ``vla``, the steered policy's options
(``policy``: the VLA family's policy name, default ``pi0_smollm2``; ``checkpoint``, ``chunk``,
``cameras``, ``state_key``, ... as :class:`~infinirl.models.vla.policy.PiZeroPolicy` takes them;
``action_dim`` is the wrapped env's), ``noise_bound``, and ``reward_offset``, added to every
decision's reward (DSRL's -1 with a success reward that ends the episode: every decision before
success costs one, so the value is minus the decisions still to come and solving sooner is worth
more, whatever entropy bonus an off-policy learner adds).

The VLA is loaded once per process and shared by that process's sub-envs. It acts on one env at a
time (batch 1): the runner steps sub-envs one by one, so nothing could be batched here anyway.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from infinirl.envs.base import ActionSpace, ArraySpec, Obs, SubStep, step_takes_observe
from infinirl.envs.options import EnvOptions

__all__ = ["FEATURES", "NoiseSteeringFactory", "NoiseSteeringSubEnv", "noise_steering_factory",
           "noise_steering_options"]

FEATURES = "features"
"""The observation field: the frozen VLA's features of the wrapped env's observation."""

_OWN_OPTIONS = ("vla", "noise_bound", "reward_offset")
_POLICIES: dict[str, Any] = {}  # options (as JSON) -> the steered policy, one per process


def _steered_policy(options: Mapping[str, Any], action_dim: int):
    """The steered policy for ``options`` (built once per process and shared)."""
    key = json.dumps({**options, "action_dim": action_dim}, sort_keys=True)
    if key not in _POLICIES:
        import infinirl.models.vla.steered  # noqa: F401  (registers the steered policies)
        from infinirl.models.policies.base import POLICIES

        kwargs = dict(options)
        family = kwargs.pop("policy", "pi0_smollm2")
        if f"{family}_steered" not in POLICIES:
            steerable = sorted(name.removesuffix("_steered") for name in POLICIES.names() if name.endswith("_steered"))
            raise ValueError(f"vla.policy={family!r} is not a VLA that can be steered; one of {', '.join(steerable)}")
        policy = POLICIES.get(f"{family}_steered")(action_dim=action_dim, value_head=False, **kwargs)
        _POLICIES[key] = policy.eval().requires_grad_(False)
    return _POLICIES[key]


def _batch_of_one(obs: Obs) -> dict[str, Any]:
    import torch

    return {key: [value] if isinstance(value, str) else torch.as_tensor(np.asarray(value)[None])
            for key, value in obs.items()}


class NoiseSteeringSubEnv:
    """One wrapped sub-env whose action is the VLA's initial noise (see the module docstring)."""

    def __init__(self, inner: Any, vla: Mapping[str, Any], noise_bound: float, reward_offset: float = 0.0):
        self.inner, self.reward_offset = inner, float(reward_offset)
        self._inner_observes = step_takes_observe(inner)
        self.policy = _steered_policy(vla, int(np.prod(inner.action_space.shape)))
        size = int(np.prod(self.policy.noise_shape))
        self.action_space = ActionSpace.box(np.full(size, -noise_bound), np.full(size, noise_bound))
        width = self.policy.vla.config.architecture.vlm.width + self.policy.vla.config.max_state_dim
        self.observation_spec = {FEATURES: ArraySpec((width,), "float32")}
        self._inputs = self._prefix = None  # of the observation the next step decodes from

    def _observe(self, obs: Obs) -> Obs:
        import torch

        with torch.no_grad():
            features, self._inputs, self._prefix = self.policy.features(_batch_of_one(obs))
        return {FEATURES: features[0].numpy().astype(np.float32)}

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs:
        return self._observe(self.inner.reset(seed=seed, state_id=state_id))

    def step(self, action: np.ndarray) -> SubStep:
        import torch

        noise = torch.as_tensor(np.asarray(action, np.float32)).reshape(1, *self.policy.noise_shape)
        chunk = self.policy.decode(self._inputs, self._prefix, noise)[0].numpy()
        reward, success, result = self.reward_offset, False, None
        for k, env_action in enumerate(chunk):
            last = k == len(chunk) - 1
            result = (self.inner.step(env_action, observe=last) if self._inner_observes
                      else self.inner.step(env_action))
            reward += result.reward
            success |= result.success
            if result.terminated or result.truncated:
                break
        return SubStep(self._observe(result.obs), reward, result.terminated, result.truncated, success)

    def render(self) -> np.ndarray:
        return self.inner.render()

    def close(self) -> None:
        self.inner.close()


@dataclass(frozen=True)
class NoiseSteeringFactory:
    """Picklable ``index -> NoiseSteeringSubEnv`` over the wrapped family's factory."""

    inner: Any
    vla: Mapping[str, Any] = field(default_factory=dict)
    noise_bound: float = 1.5
    reward_offset: float = 0.0

    def __call__(self, index: int) -> NoiseSteeringSubEnv:
        return NoiseSteeringSubEnv(self.inner(index), self.vla, self.noise_bound, self.reward_offset)

    def task_names(self, num_envs: int) -> list[str] | None:
        names = getattr(self.inner, "task_names", None)
        return names(num_envs) if callable(names) else None


def noise_steering_factory(task: str | None, *, vla: Mapping[str, Any] | None = None, noise_bound: float = 1.5,
                           reward_offset: float = 0.0, **inner_kwargs: Any) -> NoiseSteeringFactory:
    """Registry entry: ``vla_noise:<family>:<task>``; ``vla`` must name a ``checkpoint``."""
    from infinirl.envs.registry import ENVS, split_env_name

    if not task:
        raise ValueError("vla_noise wraps another env: write vla_noise:<family>:<task>, e.g. "
                         "vla_noise:metaworld:door-open-v3")
    if not vla or "checkpoint" not in vla:
        raise ValueError("vla_noise needs the option vla.checkpoint (the flow VLA's folder, e.g. the one "
                         "`infinirl train sft_vla_metaworld` writes to runs/sft_vla_metaworld/policy)")
    if "action_dim" in vla:
        raise ValueError("vla.action_dim is the wrapped env's; remove it")
    if not noise_bound > 0:
        raise ValueError(f"noise_bound must be > 0, got {noise_bound!r}")
    if not np.isfinite(reward_offset):
        raise ValueError(f"reward_offset must be a finite number, got {reward_offset!r}")
    family, inner_task = split_env_name(task)
    return NoiseSteeringFactory(ENVS.get(family)(inner_task, **inner_kwargs), dict(vla), float(noise_bound),
                                float(reward_offset))


def noise_steering_options(task: str | None) -> EnvOptions:
    """The wrapped env's options and this wrapper's own (``vla``, ``noise_bound``, ``reward_offset``)."""
    from infinirl.envs.registry import env_options

    if not task:
        return EnvOptions(names=frozenset(_OWN_OPTIONS))
    inner = env_options(task)
    # the wrapped env keeps its own time limit: the wrapper's (make_env's) counts decisions, not its steps
    return EnvOptions(names=(inner.names - {"max_episode_steps"}) | set(_OWN_OPTIONS),
                      passes_others=inner.passes_others, reserved=inner.reserved, choices=inner.choices)
