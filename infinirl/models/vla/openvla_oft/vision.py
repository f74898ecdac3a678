"""OpenVLA's vision side: timm-layout ViT embeddings around transformers' encoder layers, and the projector.

OpenVLA runs timm's ``vit_large_patch14_reg4_dinov2`` and ``vit_so400m_patch14_siglip_224`` and
keeps the output of the *second-to-last* block, patch tokens only, without the final norm
(``get_intermediate_layers(n={depth - 2})``). So only ``depth - 1`` blocks are built here: the last
block, the final norm and SigLIP's attention-pool head exist in the checkpoint but never touch the
features, and :mod:`.checkpoint` skips them by name.

The blocks are transformers' ``Dinov2WithRegistersLayer`` (layer scale) and ``SiglipEncoderLayer``
with exact GELU (timm's default; transformers' SigLIP default is the tanh approximation). The
embeddings keep timm's parameter layout: DINOv2's ``pos_embed`` covers the patches only
(``no_embed_class``), then ``[cls, registers, patches]``; SigLIP has neither class token nor registers.
"""

from __future__ import annotations

import torch
from torch import nn
from transformers import Dinov2WithRegistersConfig, SiglipVisionConfig
from transformers.models.dinov2_with_registers.modeling_dinov2_with_registers import Dinov2WithRegistersLayer
from transformers.models.siglip.modeling_siglip import SiglipEncoderLayer

from infinirl.models.vla.openvla_oft.config import OFTConfig, ViTSpec

__all__ = ["FusedVision", "Projector", "ViTFeaturizer"]

LAYER_NORM_EPS = 1e-6  # timm's ViT LayerNorm


def _layer(spec: ViTSpec, attention: str) -> nn.Module:
    if spec.kind == "dinov2":
        if spec.mlp_dim % spec.width:
            raise ValueError(f"DINOv2 mlp_dim {spec.mlp_dim} must be a multiple of its width {spec.width}")
        config = Dinov2WithRegistersConfig(hidden_size=spec.width, num_attention_heads=spec.num_heads,
                                           mlp_ratio=spec.mlp_dim // spec.width, hidden_act="gelu",
                                           layer_norm_eps=LAYER_NORM_EPS, qkv_bias=True,
                                           num_register_tokens=spec.register_tokens)
        config._attn_implementation = attention
        return Dinov2WithRegistersLayer(config)
    if spec.kind == "siglip":
        config = SiglipVisionConfig(hidden_size=spec.width, intermediate_size=spec.mlp_dim,
                                    num_attention_heads=spec.num_heads, hidden_act="gelu",
                                    layer_norm_eps=LAYER_NORM_EPS)
        config._attn_implementation = attention
        return SiglipEncoderLayer(config)
    raise ValueError(f"unknown ViT kind {spec.kind!r}")


class ViTFeaturizer(nn.Module):
    """One ViT up to its second-to-last block: ``[B, 3, S, S]`` -> patch features ``[B, P, width]``."""

    def __init__(self, spec: ViTSpec, attention: str = "sdpa"):
        super().__init__()
        self.spec = spec
        self.patch_embed = nn.Conv2d(3, spec.width, kernel_size=spec.patch_size, stride=spec.patch_size)
        self.pos_embed = nn.Parameter(torch.zeros(1, spec.num_patches, spec.width))
        self.prefix = (1 + spec.register_tokens) if spec.kind == "dinov2" else 0
        if spec.kind == "dinov2":
            self.cls_token = nn.Parameter(torch.zeros(1, 1, spec.width))
            self.reg_token = nn.Parameter(torch.zeros(1, spec.register_tokens, spec.width))
        self.blocks = nn.ModuleList(_layer(spec, attention) for _ in range(spec.depth - 1))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        x = self.patch_embed(pixels).flatten(2).transpose(1, 2) + self.pos_embed
        if self.prefix:
            batch = x.shape[0]
            x = torch.cat([self.cls_token.expand(batch, -1, -1), self.reg_token.expand(batch, -1, -1), x], dim=1)
        for block in self.blocks:
            # no padding inside an image: SigLIP's layer takes the (absent) mask positionally, DINOv2's
            # takes none in some transformers releases, so it is given only where required
            x = block(x, None) if self.spec.kind == "siglip" else block(x)
        return x[:, self.prefix:]


class FusedVision(nn.Module):
    """DINOv2 (+ SigLIP) features of each image, concatenated along the width; images one after another.

    ``pixels``: ``[B, N * 3 * len(vision), S, S]``: per image, 3 channels per backbone (OFT's layout)."""

    def __init__(self, config: OFTConfig, attention: str = "sdpa"):
        super().__init__()
        self.featurizers = nn.ModuleList(ViTFeaturizer(spec, attention) for spec in config.vision)
        self.num_images = config.num_images
        self.width = sum(spec.width for spec in config.vision)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        per_image = 3 * len(self.featurizers)
        expected = per_image * self.num_images
        if pixels.dim() != 4 or pixels.shape[1] != expected:
            raise ValueError(f"pixel_values of shape {list(pixels.shape)}: expected [B, {expected}, S, S] "
                             f"({self.num_images} image(s) x 3 channels x {len(self.featurizers)} backbone(s))")
        patches = []
        for image in pixels.split(per_image, dim=1):
            parts = image.split(3, dim=1)
            patches.append(torch.cat([f(part) for f, part in zip(self.featurizers, parts, strict=True)], dim=2))
        return torch.cat(patches, dim=1)


class Projector(nn.Module):
    """Prismatic's MLP projector: ``fc1-GELU-fc2`` (one backbone) or ``fc1-GELU-fc2-GELU-fc3`` (fused, 4x wide)."""

    def __init__(self, vision_dim: int, llm_dim: int, fused: bool):
        super().__init__()
        self.fused = fused
        hidden = 4 * vision_dim if fused else llm_dim
        self.fc1 = nn.Linear(vision_dim, hidden)
        self.fc2 = nn.Linear(hidden, llm_dim)
        self.fc3 = nn.Linear(llm_dim, llm_dim) if fused else None
        self.act = nn.GELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.fc2(self.act(self.fc1(x)))
        return self.fc3(self.act(x)) if self.fc3 is not None else x
