"""The policy as the embodied rollout and actor both hold it: a registered :class:`Policy` plus a
running observation normaliser, in one ``nn.Module`` so weight sync and checkpoints carry both.

* :class:`~infinirl.models.running_stats.RunningMeanStd` (defined in ``models``, where the SAC
  state normaliser and the residual VLA policy also use it): Chan et al.'s parallel mean/variance
  update, kept as module *buffers*, so the trainer's statistics reach the rollout with every
  weight sync and are restored on resume.
* :class:`NormalizedPolicy`: normalises the float observation fields it was told to (``state``,
  ``proprio``; never ``rgb``), clips them to ``[-clip, clip]``, and delegates ``act`` /
  ``evaluate`` / ``value`` to the wrapped policy. Only the trainer updates the statistics, from
  each batch *after* its PPO update (so the batch is trained with the statistics the rollout
  used: the PPO ratio starts at exactly 1).
* :class:`ReturnNormalizer`: PPO reward scaling (Engstrom et al. 2020, "Implementation Matters"):
  rewards divided by the running std of each env's discounted return. Pure state, checkpointed by
  the runner.
* :func:`policy_kwargs`: fills a policy constructor's shape arguments (``obs_dim``,
  ``action_dim``, ``chunk``, ``image_shape``, ``proprio_dim``, ``low``/``high``) from the env's
  observation spec and action space, so configs name only what they choose.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from infinirl.models.policies.base import POLICIES, Policy, PolicyEval, PolicyStep
from infinirl.models.running_stats import RunningMeanStd

__all__ = ["NormalizedPolicy", "ReturnNormalizer", "RunningMeanStd", "build_embodied_policy", "compute_device",
           "critic_lr_of", "module_device", "policy_kwargs"]

COMPUTE_DEVICES = ("auto", "cpu")


def compute_device(placed_on: str, setting: str) -> torch.device:
    """Where an embodied worker computes: ``setting="auto"`` uses the device its placement gave it
    (``placed_on``: ``"cuda"`` for a rank holding a GPU, else ``"cpu"``); ``"cpu"`` keeps the
    policy on the CPU even on a GPU (a small MLP's tiny ops cost less on CPU than as kernel
    launches, and its env's observations arrive in host memory anyway)."""
    if setting not in COMPUTE_DEVICES:
        raise ValueError(f"device={setting!r}: use one of {list(COMPUTE_DEVICES)}")
    return torch.device("cpu" if setting == "cpu" else placed_on)


def critic_lr_of(policy: nn.Module, lr: float, value_lr: float):
    """``name -> learning rate`` for ``policy``'s parameters (a :class:`Policy`, or a wrapper holding
    one as ``.policy``): ``value_lr`` under its ``critic_modules``, ``lr`` elsewhere (names may carry
    a wrapper's prefix)."""
    inner = getattr(policy, "policy", policy)
    modules = tuple(getattr(inner, "critic_modules", ()))

    def lr_of(name: str) -> float:
        dotted = f".{name}."
        return value_lr if any(f".{module}." in dotted for module in modules) else lr

    return lr_of


def module_device(module: nn.Module) -> torch.device:
    """The device of a module's first parameter or buffer (CPU for one with neither)."""
    for tensor in module.parameters():
        return tensor.device
    for tensor in module.buffers():
        return tensor.device
    return torch.device("cpu")


class NormalizedPolicy(nn.Module):
    """A :class:`Policy` behind a running normaliser of the observation fields ``keys``.

    ``keys`` empty: a transparent wrapper (the same module layout either way, so checkpoints and
    weight sync never depend on the option).
    """

    def __init__(self, policy: Policy, obs_shapes: Mapping[str, Sequence[int]], clip: float = 10.0):
        super().__init__()
        self.policy = policy
        self.clip = float(clip)
        self.keys = sorted(obs_shapes)
        self.obs_rms = nn.ModuleDict({key: RunningMeanStd(shape) for key, shape in obs_shapes.items()})

    @property
    def chunk(self) -> int:
        return int(getattr(self.policy, "chunk", 1))

    def normalize(self, obs: Mapping[str, Any]) -> dict[str, Any]:
        out = dict(obs)
        for key in self.keys:
            out[key] = self.obs_rms[key].normalize(obs[key], self.clip)
        return out

    @property
    def held_noise_every(self) -> int:
        return int(getattr(self.policy, "held_noise_every", 0))

    def hold_noise(self, seed: int) -> None:
        self.policy.hold_noise(seed)

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        return self.policy.act(self.normalize(obs), deterministic=deterministic)

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        return self.policy.evaluate(self.normalize(obs), actions, extras=extras, with_entropy=with_entropy)

    def value(self, obs) -> torch.Tensor:
        return self.policy.value(self.normalize(obs))

    def forward(self, obs, actions, extras=None, with_entropy: bool = True, obs_normalized: bool = False, *,
                demo_mask: torch.Tensor | None = None):
        """``evaluate`` as a tuple ``(logprobs, entropy, values)``: the call FSDP2's hooks see.
        ``obs_normalized``: ``obs`` already went through :meth:`normalize` (the trainer normalises a
        whole batch once, its statistics being fixed during an update).

        ``demo_mask`` given: ``obs`` / ``actions`` are dataset frames, ``demo_mask`` their validity
        and ``extras`` their draws, and the result is the policy's
        :meth:`~infinirl.models.policies.base.Policy.demo_loss` (through ``forward`` too, so a
        sharded model gathers its weights for it as for the PPO loss)."""
        if demo_mask is not None:
            return self.policy.demo_loss(obs, actions, action_mask=demo_mask, draws=extras)
        if obs_normalized:
            out = self.policy.evaluate(obs, actions, extras=extras, with_entropy=with_entropy)
        else:
            out = self.evaluate(obs, actions, extras=extras, with_entropy=with_entropy)
        return out.logprobs, out.entropy, out.values

    @torch.no_grad()
    def fit_input_stats(self, extras: Mapping[str, torch.Tensor] | None) -> None:
        """Lets a policy that standardises inputs of its own (the residual VLA's
        ``residual_input_norm``) fit them on a training batch's ``extras``, before the update."""
        fit = getattr(self.policy, "fit_input_stats", None)
        if fit is not None:
            fit(extras)

    @torch.no_grad()
    def fit_readout(self, obs: Mapping[str, torch.Tensor], extras: Mapping[str, torch.Tensor] | None) -> dict:
        """Lets a policy with a readout fitted on training batches (the residual VLA's
        ``residual_readout``) fold in an updated batch's raw ``obs`` and ``extras``; its metrics."""
        fit = getattr(self.policy, "fit_readout", None)
        return fit(obs, extras) if fit is not None else {}

    @torch.no_grad()
    def update_obs_stats(self, obs: Mapping[str, torch.Tensor]) -> None:
        for key in self.keys:
            self.obs_rms[key].update(obs[key])


class ReturnNormalizer:
    """Divides rewards by the running std of each env's discounted return (no mean shift).

    ``scale(rewards [T, N], dones [T, N])`` walks the rollout in time order, keeping one running
    return per env across calls (reset where an episode ended), folds the returns into the
    statistics, and returns ``rewards / sqrt(var + eps)``. Its state is a plain dict for
    checkpoints.
    """

    def __init__(self, num_envs: int, gamma: float, epsilon: float = 1e-8):
        self.gamma, self.epsilon = gamma, epsilon
        self.returns = np.zeros(num_envs, dtype=np.float64)
        self.rms = RunningMeanStd(())

    def scale(self, rewards: torch.Tensor, dones: torch.Tensor) -> torch.Tensor:
        rewards64 = rewards.detach().cpu().to(torch.float64).numpy()
        dones_np = dones.detach().cpu().numpy().astype(bool)
        if rewards64.ndim == 3:  # per-action rewards of chunks: their sum is the step's reward
            step_rewards = rewards64.sum(-1)
        else:
            step_rewards = rewards64
        seen = np.empty_like(step_rewards)
        for t in range(step_rewards.shape[0]):
            self.returns = self.returns * self.gamma + step_rewards[t]
            seen[t] = self.returns
            self.returns[dones_np[t]] = 0.0
        self.rms.update(torch.from_numpy(seen.reshape(-1)))
        std = float(torch.sqrt(self.rms.var + self.epsilon))
        return rewards / std

    def end_episodes(self) -> None:
        """Every env's episode ended (the next rollout resets them): their running returns restart."""
        self.returns[:] = 0.0

    def state_dict(self) -> dict:
        return {"returns": self.returns.tolist(), "mean": float(self.rms.mean), "var": float(self.rms.var),
                "count": float(self.rms.count)}

    def load_state_dict(self, state: dict) -> None:
        self.returns = np.asarray(state["returns"], dtype=np.float64)
        self.rms.mean.fill_(state["mean"])
        self.rms.var.fill_(state["var"])
        self.rms.count.fill_(state["count"])


# policy kwargs naming an observation field, and the kwarg the field's flat size fills
_OBS_FIELD_OPTIONS = (("critic_obs", "critic_obs_dim"), ("residual_readout", "residual_readout_dim"))


def _fill_field_sizes(kwargs: dict[str, Any], params, observation_spec: Mapping[str, Any]) -> None:
    """Fills the size of each observation field a policy kwarg names (``_OBS_FIELD_OPTIONS``);
    a field the env lacks is refused with the fields it has."""
    for field_key, dim_key in _OBS_FIELD_OPTIONS:
        field = kwargs.get(field_key)
        if field is None or dim_key not in params:
            continue
        if field not in observation_spec:
            raise ValueError(f"policy.kwargs.{field_key}={field!r} is not an observation field of this env; it has "
                             f"{sorted(observation_spec)}")
        kwargs.setdefault(dim_key, int(np.prod(observation_spec[field].shape)))


def policy_kwargs(name: str, options: Mapping[str, Any], observation_spec: Mapping[str, Any], action_space,
                  chunk: int) -> dict[str, Any]:
    """The constructor arguments of registered policy ``name``: ``options`` plus the shape
    arguments its signature takes and ``options`` leaves out, read from the env's specs."""
    cls = _policy_class(name)
    params = inspect.signature(cls.__init__).parameters
    kwargs = dict(options)

    def fill(key: str, value: Any) -> None:
        if key in params and key not in kwargs:
            kwargs[key] = value

    if action_space.is_discrete:
        fill("num_actions", int(action_space.num_choices))
        fill("action_dim", 1)
    else:
        fill("action_dim", int(np.prod(action_space.shape)))
        if "low" in params and "low" not in kwargs:
            kwargs["low"] = [float(v) for v in np.asarray(action_space.low).reshape(-1)]
            kwargs["high"] = [float(v) for v in np.asarray(action_space.high).reshape(-1)]
    fill("chunk", chunk)
    obs_key = kwargs.get("obs_key", _default(params, "obs_key", "state"))
    if obs_key in observation_spec:
        fill("obs_dim", int(np.prod(observation_spec[obs_key].shape)))
    rgb_key = kwargs.get("rgb_key", _default(params, "rgb_key", "rgb"))
    if rgb_key in observation_spec:
        fill("image_shape", tuple(observation_spec[rgb_key].shape))
    proprio_key = kwargs.get("proprio_key", _default(params, "proprio_key", "proprio"))
    if proprio_key in observation_spec and "proprio_dim" in params and "proprio_dim" not in kwargs:
        kwargs["proprio_dim"] = int(np.prod(observation_spec[proprio_key].shape))
    _fill_field_sizes(kwargs, params, observation_spec)
    for key in ("hidden", "channels", "kernels", "strides", "value_hidden", "image_shape"):
        if isinstance(kwargs.get(key), list):
            kwargs[key] = tuple(kwargs[key])
    return kwargs


def normalized_keys(observation_spec: Mapping[str, Any], enabled: bool,
                    keys: Sequence[str] | None = None) -> dict[str, tuple[int, ...]]:
    """The float fields to normalise: ``keys`` if given, else every float32/float64 field."""
    if not enabled:
        return {}
    chosen = keys if keys else [k for k, s in observation_spec.items() if s.dtype in ("float32", "float64")]
    missing = [k for k in chosen if k not in observation_spec]
    if missing:
        raise ValueError(f"cannot normalise observation fields {missing}; the env has {sorted(observation_spec)}")
    return {key: tuple(observation_spec[key].shape) for key in chosen}


def build_embodied_policy(name: str, options: Mapping[str, Any], observation_spec, action_space, chunk: int,
                          normalize_obs: bool, normalize_keys: Sequence[str] | None = None,
                          obs_clip: float = 10.0) -> NormalizedPolicy:
    """The registered policy ``name`` wrapped in its observation normaliser."""
    from infinirl.models.policies.base import build_policy

    policy = build_policy(name, **policy_kwargs(name, options, observation_spec, action_space, chunk))
    shapes = normalized_keys(observation_spec, normalize_obs, normalize_keys)
    return NormalizedPolicy(policy, shapes, obs_clip)


def registered_policies() -> list[str]:
    from infinirl.models.policies.base import _import_builtin_policies

    _import_builtin_policies()
    return POLICIES.names()


def _policy_class(name: str) -> type:
    registered_policies()
    return POLICIES.get(name)


def _default(params, key: str, fallback: str) -> str:
    if key in params and params[key].default is not inspect.Parameter.empty:
        return params[key].default
    return fallback
