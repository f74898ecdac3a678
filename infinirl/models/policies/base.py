"""The one interface every embodied policy implements (MLP, CNN, flow-matching, later VLAs).

Runners and the PPO/GRPO/SAC code only ever call :meth:`Policy.act` (rollout side) and
:meth:`Policy.evaluate` (trainer side), so a new policy family is a new module plus one
``@POLICIES.register`` line, never an edit of a runner.

Shapes (``B`` = batch of envs, ``K`` = action-chunk length, ``A`` = action dims):

* ``actions``: ``[B, K, A]`` float for continuous spaces, ``[B, K]`` long for discrete ones.
* ``logprobs`` / ``entropy``: ``[B, K]``: one number per action of the chunk (summed over the
  action dims), so advantages can be credited per action *or* per chunk (sum over ``K``).
* ``values``: ``[B]``: one value per observation (the chunk is one decision).
* ``extras``: tensors the rollout must hand back to :meth:`evaluate` to recompute the same
  log-probabilities (a flow policy's denoising trajectory; empty for Gaussian heads). They travel
  with the batch, so the trainer never re-samples.

Observations arrive as a dict of tensors with a leading batch dim (``state``, ``proprio``,
``rgb`` uint8 ``[B, H, W, 3]``); ``prepare_obs`` turns the env's numpy dict into that.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from infinirl.registry import Registry

POLICIES: Registry[type] = Registry("policy", entry_point_group="infinirl.policies")


@dataclass
class PolicyStep:
    """What :meth:`Policy.act` returns for a batch of observations."""

    actions: torch.Tensor
    logprobs: torch.Tensor
    values: torch.Tensor | None = None
    extras: dict[str, torch.Tensor] = field(default_factory=dict)


@dataclass
class PolicyEval:
    """What :meth:`Policy.evaluate` returns: differentiable log-probs (and entropy, values)."""

    logprobs: torch.Tensor
    entropy: torch.Tensor | None = None
    values: torch.Tensor | None = None


class Policy(nn.Module):
    """Base class: subclasses set ``action_dim``/``chunk`` and implement ``act``/``evaluate``."""

    action_dim: int
    chunk: int = 1
    has_value_head: bool = False
    joint_chunk_logprob: bool = False
    """The ``K`` rows of a chunk's log-probs split one joint likelihood (a flow policy denoises the
    chunk jointly, so its rows are not separate draws): at chunk level PPO takes the decision's
    log-prob as the sum over all ``K`` rows, executed or not (an episode that ended mid-chunk still
    sampled the rest). False: each row is its own action's likelihood, and only executed rows count."""
    critic_modules: tuple[str, ...] = ()
    """Names of the submodules that form the critic (``actor.value_lr`` trains them at its rate)."""
    lora_refusal: str | None = None
    """Why ``actor.lora`` cannot apply to this policy (refused before any worker starts); None: it can."""
    fresh_modules: tuple[str, ...] = ()
    """Submodules with no pretrained weights besides the value head (e.g. a learned exploration-noise
    head): ``actor.lora`` trains them in full whatever ``train_fully`` names, as adapters on a
    zero-initialised layer would be a low-rank copy of a layer that should learn freely."""
    demo_refusal: str | None = "it has no loss on LeRobotDataset frames (demo_loss)"
    """Why PPO's behaviour-cloning anchor (``algorithm.bc``) cannot train this policy on a dataset of
    demonstrations (refused before any worker starts); None: :meth:`demo_loss` is implemented."""

    normalizes_own_inputs: bool = False
    """The policy normalises its observation inputs itself (a VLA, with its checkpoint's statistics): the
    runner's running normaliser (``policy.normalize_obs``) would normalise them twice and is refused."""

    held_noise_every: int = 0
    """Decisions for which part of the exploration noise is held (0: none): the rollout then calls
    :meth:`hold_noise` before each sampled decision with a seed that changes every
    ``held_noise_every`` decisions of an env stage."""

    def hold_noise(self, seed: int) -> None:
        """The seed of the held part of the next sampled :meth:`act`'s noise (policies with
        ``held_noise_every > 0``)."""

    def act(self, obs: dict[str, torch.Tensor], deterministic: bool = False) -> PolicyStep:
        raise NotImplementedError

    def evaluate(self, obs: dict[str, torch.Tensor], actions: torch.Tensor,
                 extras: dict[str, torch.Tensor] | None = None, with_entropy: bool = True) -> PolicyEval:
        raise NotImplementedError

    def value(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        raise NotImplementedError(f"{type(self).__name__} has no value head")

    @property
    def demo_chunk(self) -> int:
        """Actions per demonstration chunk :meth:`demo_loss` takes (a VLA's whole ``chunk_size``)."""
        return self.chunk

    def demo_draws(self, batch: int) -> dict[str, torch.Tensor]:
        """The random draws :meth:`demo_loss` needs for ``batch`` frames (a flow-matching policy's
        noise and times; row ``i`` is frame ``i``'s), from torch's global generator. Drawn for a
        whole batch and sliced per rank, so data-parallel ranks clone as one would."""
        return {}

    def demo_loss(self, observation: dict[str, Any], actions: torch.Tensor, action_mask: torch.Tensor | None = None,
                  draws: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """The cloning loss on dataset frames: ``observation`` in the dataset's LeRobot keys
        (``observation.images.<camera>``, ``observation.state``, ``task``), ``actions``
        ``[B, demo_chunk, A]`` in env units, ``action_mask`` ``[B, demo_chunk]`` the real rows,
        ``draws`` these frames' rows of :meth:`demo_draws` (None: drawn here)."""
        raise NotImplementedError(f"{type(self).__name__}: {self.demo_refusal}")


def prepare_obs(obs: dict[str, Any], device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Env numpy observations -> tensors (text fields such as ``instruction`` are left as lists)."""
    out: dict[str, Any] = {}
    for key, value in obs.items():
        if isinstance(value, np.ndarray) and value.dtype.kind in "USO":  # text: one string per env
            out[key] = value.tolist()
        elif isinstance(value, np.ndarray):
            out[key] = torch.as_tensor(value, device=device)
        elif isinstance(value, torch.Tensor):
            out[key] = value.to(device)
        else:
            out[key] = value
    return out


def build_policy(name: str, **kwargs) -> Policy:
    """Instantiate a registered policy (``mlp_gaussian``, ...) with its keyword options."""
    _import_builtin_policies()
    cls = POLICIES.get(name)
    _check_switches(cls, kwargs)
    return cls(**kwargs)


def _check_switches(cls: type, kwargs: dict) -> None:
    """Options declared ``bool`` in any ``__init__`` along the class's MRO must be booleans: a
    config's ``residual_pixels=maybe`` is a string, which Python would take as true."""
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        for option, annotation in getattr(init, "__annotations__", {}).items():
            if annotation in ("bool", bool) and option in kwargs and not isinstance(kwargs[option], bool):
                raise ValueError(f"{option} must be true or false, got {kwargs[option]!r}")


def _import_builtin_policies() -> None:
    import importlib
    import pkgutil

    import infinirl.models.policies as package

    for module in pkgutil.iter_modules(package.__path__):
        if module.name != "base":
            importlib.import_module(f"{package.__name__}.{module.name}")
