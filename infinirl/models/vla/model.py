"""The π0 / π0.5 network: SigLIP + PaliGemma prefix, Gemma action expert, flow-matching head.

The same network, with the stack and vision kinds its architecture names (:mod:`.layers`,
:mod:`.vision`), is the small ``pi0_smollm2`` family: SmolLM2's first layers (Llama) as the
language model, a conv stem for the images, a narrow Llama action expert.

Conventions are π0's (openpi, LeRobot): flow time ``t`` runs from 1 (noise) to 0 (action),
``x_t = t * noise + (1 - t) * action``, and the network predicts ``v = noise - action``; sampling
integrates ``x <- x + dt * v`` with ``dt = -1 / num_steps`` from ``x_1 = noise``. (The repo's flow
policies write the same path with ``tau = 1 - t`` and velocity ``-v``; :mod:`.policy` converts.)

Token layout (one sequence, :func:`~.layers.block_mask` blocks):

* prefix: each camera's SigLIP tokens projected to the VLM width, then the instruction's token
  embeddings times ``sqrt(width)``; bidirectional among valid tokens. Missing cameras and padding
  tokens are masked out.
* suffix (action expert): π0 puts one state token (``state_proj``) in a block of its own, then the
  ``chunk_size`` action tokens in one block (bidirectional among themselves, seeing everything
  before). π0.5 has no state token (the state is in the prompt) and conditions the expert's
  norms on time (adaRMS) instead of mixing time into each action token.

Inference embeds the prefix once, keeps its per-layer keys/values (:class:`PrefixCache`), and runs
only the expert for each denoising step (:meth:`PiZero.velocity`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from infinirl.models.vla.config import VLAConfig
from infinirl.models.vla.layers import (
    DecoderStack,
    KVCache,
    Stream,
    attention_bias,
    block_mask,
    mixture_forward,
)
from infinirl.models.vla.vision import VISION_TOWERS

__all__ = ["PiZero", "PrefixCache", "time_embedding"]


def time_embedding(time: torch.Tensor, dim: int, min_period: float, max_period: float) -> torch.Tensor:
    """openpi's sine-cosine embedding of scalar times ``[B]`` -> ``[B, dim]`` (computed in float64,
    returned in ``time``'s dtype), periods geometric from ``min_period`` to ``max_period``."""
    if dim % 2:
        raise ValueError(f"the time embedding needs an even width, got {dim}")
    fraction = torch.linspace(0.0, 1.0, dim // 2, dtype=torch.float64, device=time.device)
    period = min_period * (max_period / min_period) ** fraction
    angle = (2 * math.pi / period)[None, :] * time[:, None]
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=1).to(time.dtype)


@dataclass
class PrefixCache:
    """The embedded prefix as the denoising steps need it."""

    kv: KVCache
    pad_mask: torch.Tensor
    hidden: torch.Tensor


class PiZero(nn.Module):
    """π0 (``config.family == "pi0"``) or π0.5 (``"pi05"``); weights named as :mod:`.checkpoint` maps."""

    def __init__(self, config: VLAConfig):
        super().__init__()
        self.config = config
        arch, switches = config.architecture, config.switches
        build_vision = VISION_TOWERS.get(arch.vision.kind)
        self.vision_tower, self.projector = build_vision(arch.vision, config.image_resolution[0], arch.vlm.width)
        width = arch.expert.width
        self.vlm = DecoderStack(arch.vlm, arch.vocab_size, embed=True)
        self.expert = DecoderStack(arch.expert, arch.vocab_size, embed=False,
                                   cond_dim=width if switches.adarms_time else None)
        self.rotary = self.vlm.rotary_embedding()
        self.action_in_proj = nn.Linear(config.max_action_dim, width)
        self.action_out_proj = nn.Linear(width, config.max_action_dim)
        if switches.adarms_time:
            self.time_mlp_in = nn.Linear(width, width)
            self.time_mlp_out = nn.Linear(width, width)
        else:
            self.action_time_mlp_in = nn.Linear(2 * width, width)
            self.action_time_mlp_out = nn.Linear(width, width)
        if not switches.discrete_state:
            self.state_proj = nn.Linear(config.max_state_dim, width)

    @property
    def dtype(self) -> torch.dtype:
        return self.action_in_proj.weight.dtype

    # --- prefix ------------------------------------------------------------------------------

    def embed_images(self, images: torch.Tensor) -> torch.Tensor:
        """Image tokens (SigLIP's or the conv stem's) projected to the VLM width: ``[B, 3, R, R]`` in
        ``[-1, 1]`` -> ``[B, N, W]``."""
        resolution = self.config.image_resolution[0]
        if images.dim() != 4 or tuple(images.shape[1:]) != (3, resolution, resolution):
            raise ValueError(f"the vision tower takes images [B, 3, {resolution}, {resolution}] in [-1, 1], got "
                             f"{list(images.shape)}: resize them first (VLAProcessor.images does)")
        features = self.vision_tower(pixel_values=images.to(self.dtype)).last_hidden_state
        return self.projector(features)

    def embed_prefix(self, images: list[torch.Tensor], image_masks: list[torch.Tensor], tokens: torch.Tensor,
                     token_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Prefix embeddings ``[B, P, W]`` and their validity mask ``[B, P]``."""
        embeddings, masks = [], []
        for image, mask in zip(images, image_masks, strict=True):
            embedded = self.embed_images(image)
            embeddings.append(embedded)
            masks.append(mask[:, None].expand(-1, embedded.shape[1]))
        if tokens.shape[1] > self.config.tokenizer_max_length:
            raise ValueError(f"{tokens.shape[1]} instruction tokens exceed the checkpoint's tokenizer_max_length "
                             f"{self.config.tokenizer_max_length}")
        embeddings.append(self.vlm.embed(tokens))
        masks.append(token_mask.bool())
        return torch.cat(embeddings, dim=1), torch.cat(masks, dim=1)

    def encode_prefix(self, images, image_masks, tokens, token_mask) -> PrefixCache:
        """Run the VLM over the prefix once; its keys/values serve every denoising step."""
        embeddings, pad_mask = self.embed_prefix(images, image_masks, tokens, token_mask)
        mask = block_mask(pad_mask, torch.zeros_like(pad_mask))
        positions = torch.cumsum(pad_mask.long(), dim=1) - 1
        (hidden,), kv = mixture_forward([Stream(self.vlm, embeddings)], attention_bias(mask, embeddings.dtype),
                                        positions, self.rotary, keep_cache=True)
        return PrefixCache(kv=kv, pad_mask=pad_mask, hidden=hidden)

    # --- suffix ------------------------------------------------------------------------------

    def embed_suffix(self, state: torch.Tensor | None, x_t: torch.Tensor,
                     time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Suffix embeddings ``[B, S, W]``, their block starts ``[B, S]`` and the adaRMS condition."""
        batch, width = x_t.shape[0], self.config.architecture.expert.width
        # from times in at least float32, cast after (as openpi): bfloat16 keeps 8 bits of t, which would
        # turn the fastest features (periods down to 4e-3) by a quarter period
        precise = time.to(torch.promote_types(self.dtype, torch.float32))
        embedded_time = time_embedding(precise, width, self.config.min_period, self.config.max_period).to(self.dtype)
        actions = self.action_in_proj(x_t.to(self.dtype))
        if self.config.switches.adarms_time:
            cond = F.silu(self.time_mlp_out(F.silu(self.time_mlp_in(embedded_time))))
        else:
            cond = None
            mixed = torch.cat([actions, embedded_time[:, None, :].expand_as(actions)], dim=2)
            actions = self.action_time_mlp_out(F.silu(self.action_time_mlp_in(mixed)))
        pieces, blocks = [actions], [1] + [0] * (self.config.chunk_size - 1)
        if not self.config.switches.discrete_state:
            if state is None:
                raise ValueError("π0 needs the (normalised, padded) state for its state token")
            pieces.insert(0, self.state_proj(state.to(self.dtype))[:, None, :])
            blocks.insert(0, 1)
        starts = torch.tensor(blocks, dtype=torch.long, device=x_t.device)[None].expand(batch, -1)
        return torch.cat(pieces, dim=1), starts, cond

    def velocity(self, prefix: PrefixCache, state: torch.Tensor | None, x_t: torch.Tensor,
                 time: torch.Tensor, return_hidden: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """``v(x_t, t)`` ``[B, chunk, max_action_dim]`` (π0 convention) against a cached prefix; with
        ``return_hidden`` also the expert's output at the action tokens ``[B, chunk, width]`` (what
        ``action_out_proj`` reads; a noise head reads it too)."""
        suffix, starts, cond = self.embed_suffix(state, x_t, time)
        batch, length = suffix.shape[:2]
        suffix_pad = torch.ones(batch, length, dtype=torch.bool, device=suffix.device)
        prefix_visible = prefix.pad_mask[:, None, :].expand(batch, length, -1)
        mask = torch.cat([prefix_visible, block_mask(suffix_pad, starts)], dim=2)
        positions = prefix.pad_mask.long().sum(-1, keepdim=True) + torch.cumsum(suffix_pad.long(), dim=1) - 1
        (out,), _ = mixture_forward([Stream(self.expert, suffix, cond)], attention_bias(mask, suffix.dtype),
                                    positions, self.rotary, past=prefix.kv)
        hidden = out[:, -self.config.chunk_size:]
        velocity = self.action_out_proj(hidden)
        return (velocity, hidden) if return_hidden else velocity

    # --- sampling and training ---------------------------------------------------------------

    @torch.no_grad()
    def sample_actions(self, images, image_masks, tokens, token_mask, state: torch.Tensor | None,
                       noise: torch.Tensor | None = None, num_steps: int | None = None) -> torch.Tensor:
        """Euler integration of the flow ODE from ``noise`` (normalised, padded actions)."""
        num_steps = num_steps or self.config.num_inference_steps
        prefix = self.encode_prefix(images, image_masks, tokens, token_mask)
        if noise is None:
            shape = (tokens.shape[0], self.config.chunk_size, self.config.max_action_dim)
            noise = torch.randn(shape, device=tokens.device, dtype=torch.float32)
        x_t, dt = noise, -1.0 / num_steps
        for step in range(num_steps):
            time = torch.full((x_t.shape[0],), 1.0 + step * dt, dtype=torch.float32, device=x_t.device)
            x_t = x_t + dt * self.velocity(prefix, state, x_t, time)
        return x_t

    def sample_time(self, batch: int, device=None) -> torch.Tensor:
        """Training times: ``Beta(alpha, beta) * scale + offset`` (more weight near t = 1, the noise end)."""
        config = self.config
        beta = torch.distributions.Beta(torch.tensor(config.time_sampling_beta_alpha),
                                        torch.tensor(config.time_sampling_beta_beta))
        time = beta.sample((batch,)) * config.time_sampling_scale + config.time_sampling_offset
        return time.to(device=device, dtype=torch.float32)

    def joint_velocity(self, images, image_masks, tokens, token_mask, state: torch.Tensor | None,
                       x_t: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """``v(x_t, t)`` with prefix and suffix in one joint pass (no cache; gradients reach both
        stacks): what :meth:`velocity` computes against a cached prefix."""
        prefix, prefix_pad = self.embed_prefix(images, image_masks, tokens, token_mask)
        suffix, starts, cond = self.embed_suffix(state, x_t, time)
        suffix_pad = torch.ones(suffix.shape[:2], dtype=torch.bool, device=suffix.device)
        pad_mask = torch.cat([prefix_pad, suffix_pad], dim=1)
        mask = block_mask(pad_mask, torch.cat([torch.zeros_like(prefix_pad, dtype=torch.long), starts], dim=1))
        positions = torch.cumsum(pad_mask.long(), dim=1) - 1
        streams = [Stream(self.vlm, prefix), Stream(self.expert, suffix, cond)]
        (_, out), _ = mixture_forward(streams, attention_bias(mask, prefix.dtype), positions, self.rotary)
        return self.action_out_proj(out[:, -self.config.chunk_size:])

    def loss_elements(self, images, image_masks, tokens, token_mask, state: torch.Tensor | None,
                      actions: torch.Tensor, noise: torch.Tensor | None = None,
                      time: torch.Tensor | None = None) -> torch.Tensor:
        """Flow-matching squared errors ``[B, chunk, max_action_dim]`` for normalised, padded
        ``actions``; prefix and suffix in one joint pass (gradients reach both stacks)."""
        if noise is None:
            noise = torch.randn_like(actions, dtype=torch.float32)
        if time is None:
            time = self.sample_time(actions.shape[0], actions.device)
        t = time[:, None, None]
        x_t = t * noise + (1 - t) * actions
        target = noise - actions
        v_t = self.joint_velocity(images, image_masks, tokens, token_mask, state, x_t, time).float()
        return F.mse_loss(target.float(), v_t, reduction="none")
