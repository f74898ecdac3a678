"""OpenVLA-OFT as a :class:`~infinirl.models.policies.base.Policy` (registered ``openvla_oft``).

Two heads, one interface (``logprobs`` ``[B, chunk]``: per executed action, summed over its dims):

* ``head="discrete"``: each of the ``chunk_size * action_dim`` action positions is a categorical
  over the 256 action tokens (the LM head's logits at the last 256 ids of the vocabulary, divided
  by ``temperature``), as RLinf trains OpenVLA-OFT with PPO/GRPO. ``act`` samples (arg-max when
  deterministic) and records the token indices (``extras["tokens"]`` ``[B, chunk_size, action_dim]``);
  ``evaluate`` recomputes their log-probs and the entropy with gradients through the Llama and vision.
* ``head="l1"``: a diagonal Gaussian around the L1 head's regressed chunk in the normalised
  ``[-1, 1]`` action space, with a *learnable*, state-independent log-std per action dim
  (``init_log_std``); ``extras["normalized"]`` holds the sample that ``evaluate`` scores.

The env receives the first ``chunk`` actions, unnormalised with the chosen dataset's statistics
(and, on LIBERO, the gripper mapped to the env's -1 = open / +1 = close as OFT's eval does); only
those are credited. Observations: ``cameras`` lists the env's image keys, primary first;
``proprio_key`` the raw state (when the checkpoint has a proprio projector); ``instruction_key``
a list of str. An optional critic (``value_head``) reads the mean of the action positions' hidden states.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from infinirl.engines.cpu_dtype import resolve_weights_dtype
from infinirl.models.policies.base import POLICIES, Policy, PolicyEval, PolicyStep
from infinirl.models.policies.mlp import gaussian_logprob

__all__ = ["OpenVLAOFTPolicy"]


@POLICIES.register("openvla_oft")
class OpenVLAOFTPolicy(Policy):
    """An OpenVLA-OFT checkpoint acting in an env (module docstring).

    Args:
        checkpoint: the OFT folder (:func:`~infinirl.models.vla.openvla_oft.load_openvla_oft`).
        action_dim / chunk: the env's action dims (the platform's) and actions executed per decision.
        head: ``"discrete"`` or ``"l1"``; unnorm_key / platform / num_images / architecture: as the loader
            (``architecture``: an ``architecture.json`` path for non-published sizes).
        cameras: env image keys, primary first (default ``("rgb",)``, then ``"wrist_rgb"`` per extra image).
        temperature: discrete sampling temperature; init_log_std: the L1 Gaussian's initial log-std.
        value_head / value_hidden: the critic.
    """

    critic_modules = ("value_net",)
    normalizes_own_inputs = True  # the proprio, with the chosen dataset's statistics (processor)

    def __init__(self, checkpoint: str, action_dim: int, chunk: int = 1, head: str = "discrete",
                 unnorm_key: str | None = None, platform: str = "libero", num_images: int = 1,
                 architecture: str | None = None, cameras: Sequence[str] | None = None, proprio_key: str = "state",
                 instruction_key: str = "instruction", resize_images: bool = False, temperature: float = 1.0,
                 init_log_std: float = -1.0, value_head: bool = True, value_hidden: int = 256,
                 dtype: str = "float32"):
        # Imported here: the registry imports this module everywhere, transformers' models are slow to import.
        from infinirl.models.vla.openvla_oft.config import read_architecture
        from infinirl.models.vla.openvla_oft.oft import load_openvla_oft

        super().__init__()
        if temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {temperature}")
        vision = read_architecture(architecture) if architecture else None
        self.vla = load_openvla_oft(Path(checkpoint), head=head, unnorm_key=unnorm_key, platform=platform,
                                    num_images=num_images, vision=vision, resize=resize_images,
                                    dtype=resolve_weights_dtype(dtype))
        spec = self.vla.config.platform
        if action_dim != spec.action_dim or not 1 <= chunk <= spec.chunk_size:
            raise ValueError(f"the env wants chunks of {chunk} x {action_dim}, the checkpoint gives "
                             f"{spec.chunk_size} x {spec.action_dim} (chunk_size x action dims)")
        self.action_dim, self.chunk, self.head = action_dim, chunk, head
        self.cameras = tuple(cameras or ("rgb", *["wrist_rgb"] * (num_images - 1)))
        if len(self.cameras) != num_images:
            raise ValueError(f"cameras={list(self.cameras)} but num_images={num_images}")
        self.proprio_key, self.instruction_key = proprio_key, instruction_key
        self.temperature = float(temperature)
        self.log_std = nn.Parameter(torch.full((action_dim,), float(init_log_std))) if head == "l1" else None
        self.has_value_head = value_head
        width = self.vla.config.llm_dim
        self.value_net = (nn.Sequential(nn.Linear(width, value_hidden), nn.SiLU(), nn.Linear(value_hidden, 1))
                          if value_head else None)

    # --- shared ------------------------------------------------------------------------------

    def _states(self, obs: Mapping[str, Any]):
        instructions = obs[self.instruction_key]
        instructions = [instructions] if isinstance(instructions, str) else list(instructions)
        proprio = obs.get(self.proprio_key) if self.vla.model.proprio_projector is not None else None
        inputs = self.vla.inputs([obs[key] for key in self.cameras], instructions, proprio)
        return self.vla.action_states(inputs)

    def _values(self, hidden: torch.Tensor) -> torch.Tensor | None:
        if self.value_net is None:
            return None
        return self.value_net(hidden.float().mean(1)).squeeze(-1)

    def _credited(self, per_dim: torch.Tensor) -> torch.Tensor:
        """``[B, chunk_size, action_dim]`` -> executed actions, summed over dims ``[B, chunk]``."""
        return per_dim[:, :self.chunk].sum(-1)

    def _log_softmax(self, hidden: torch.Tensor) -> torch.Tensor:
        logits = self.vla.model.action_logits(hidden).float() / self.temperature
        batch = logits.shape[0]
        return torch.log_softmax(logits, -1).reshape(batch, -1, self.action_dim, logits.shape[-1])

    def _env_actions(self, normalized: torch.Tensor) -> torch.Tensor:
        # after sampling: the log-probs score the model's own (normalised) chunk, the env gets its gripper
        # convention (the processor's env_actions)
        return self.vla.processor.env_actions(normalized)[:, :self.chunk].float()

    # --- the Policy interface ----------------------------------------------------------------

    def act(self, obs, deterministic: bool = False) -> PolicyStep:
        with torch.no_grad():
            states = self._states(obs)
            hidden = states.hidden
            if self.head == "discrete":
                logp = self._log_softmax(hidden)
                if deterministic:
                    tokens = logp.argmax(-1)
                else:
                    flat = logp.reshape(-1, logp.shape[-1]).exp()
                    tokens = torch.multinomial(flat, 1).reshape(logp.shape[:-1])
                chosen = logp.gather(-1, tokens[..., None]).squeeze(-1)
                normalized = self.vla.model.token_actions(self.vla.model.slice_to_token(tokens.flatten(1)))
                extras = {"tokens": tokens}
            else:
                mean = self.vla.model.regress(hidden).float()
                log_std = self.log_std.expand_as(mean)
                normalized = mean if deterministic else mean + torch.randn_like(mean) * log_std.exp()
                chosen = gaussian_logprob(normalized, mean, log_std)
                extras = {"normalized": normalized}
            values = self._values(hidden)
        return PolicyStep(actions=self._env_actions(normalized), logprobs=self._credited(chosen), values=values,
                          extras=extras)

    def evaluate(self, obs, actions, extras=None, with_entropy: bool = True) -> PolicyEval:
        """Differentiable log-probs of what ``act`` recorded (``extras``); ``actions`` are its env-unit part."""
        key = "tokens" if self.head == "discrete" else "normalized"
        if not extras or key not in extras:
            raise ValueError(f"openvla_oft ({self.head} head).evaluate needs extras[{key!r}] from act()")
        hidden = self._states(obs).hidden
        entropy = None
        if self.head == "discrete":
            logp = self._log_softmax(hidden)
            tokens = extras["tokens"].long().to(logp.device)
            chosen = logp.gather(-1, tokens[..., None]).squeeze(-1)
            if with_entropy:
                entropy = self._credited(-(logp.exp() * logp).sum(-1))
        else:
            mean = self.vla.model.regress(hidden).float()
            log_std = self.log_std.expand_as(mean)
            chosen = gaussian_logprob(extras["normalized"].detach().float().to(mean.device), mean, log_std)
            if with_entropy:
                entropy = self._credited((0.5 + 0.5 * math.log(2 * math.pi) + log_std).expand_as(mean))
        return PolicyEval(logprobs=self._credited(chosen), entropy=entropy, values=self._values(hidden))

    def value(self, obs) -> torch.Tensor:
        if self.value_net is None:
            raise NotImplementedError("this openvla_oft policy was built with value_head=False")
        return self._values(self._states(obs).hidden)
