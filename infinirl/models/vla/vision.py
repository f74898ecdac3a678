"""Image encoders of the VLA family: camera images -> tokens at the language model's width.

Each kind (:data:`VISION_TOWERS`, named by the architecture's ``vision.kind``) builds two modules,
stored on the model as ``vision_tower`` and ``projector`` (so the published π0 key names stay):

* ``siglip``: transformers' ``SiglipVisionModel`` and PaliGemma's ``PaliGemmaMultiModalProjector``
  (π0 / π0.5's published layout);
* ``conv``: :class:`ConvStem`, a few stride-2 convolutions whose last feature map's cells become
  tokens (plus a learned position embedding), and a linear projection. A small VLA trained from
  scratch on a CPU uses it: its locality prior learns from a few hundred demonstrations, where a
  randomly initialised vision transformer needs far more data, and its four stages turn a 64 px
  image into 16 tokens, so the language model's cost, which grows with the token count, stays low.

A tower takes ``pixel_values`` ``[B, 3, R, R]`` in ``[-1, 1]`` and returns an object with
``last_hidden_state`` ``[B, N, C]``; the projector maps ``C`` to the language model's width.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutput

from infinirl.models.vla.config import ConvStemSpec, SiglipSpec
from infinirl.registry import Registry

__all__ = ["VISION_TOWERS", "ConvStem", "build_conv", "build_siglip"]


def build_siglip(spec: SiglipSpec, resolution: int, width: int) -> tuple[nn.Module, nn.Module]:
    from transformers import PaliGemmaConfig, SiglipVisionConfig, SiglipVisionModel
    from transformers.models.paligemma.modeling_paligemma import PaliGemmaMultiModalProjector

    vision = SiglipVisionConfig(hidden_size=spec.hidden_size, intermediate_size=spec.intermediate_size,
                                num_hidden_layers=spec.num_hidden_layers, num_attention_heads=spec.num_attention_heads,
                                patch_size=spec.patch_size, image_size=resolution, hidden_act="gelu_pytorch_tanh",
                                layer_norm_eps=1e-6, vision_use_head=False)
    projector = PaliGemmaConfig(vision_config=vision.to_dict(), projection_dim=width)
    projector.vision_config.projection_dim = width
    return SiglipVisionModel(vision), PaliGemmaMultiModalProjector(projector)


class ConvStem(nn.Module):
    """Stride-2 stages (3x3 conv, GroupNorm, SiLU), then the ``(R / 2^stages)^2`` cells of the last
    feature map as tokens, each plus a learned position embedding."""

    def __init__(self, spec: ConvStemSpec, resolution: int):
        super().__init__()
        stride = 2 ** len(spec.channels)
        if resolution % stride:
            raise ValueError(f"image_resolution {resolution} is not a multiple of {stride}: the conv stem's "
                             f"{len(spec.channels)} stride-2 stages need one")
        stages, previous = [], 3
        for channels in spec.channels:
            stages += [nn.Conv2d(previous, channels, kernel_size=3, stride=2, padding=1),
                       nn.GroupNorm(spec.groups, channels), nn.SiLU()]
            previous = channels
        self.stages = nn.Sequential(*stages)
        self.position = nn.Parameter(torch.randn((resolution // stride) ** 2, previous) * 0.02)

    def forward(self, pixel_values: torch.Tensor) -> BaseModelOutput:
        features = self.stages(pixel_values).flatten(2).transpose(1, 2)
        return BaseModelOutput(last_hidden_state=features + self.position)


def build_conv(spec: ConvStemSpec, resolution: int, width: int) -> tuple[nn.Module, nn.Module]:
    return ConvStem(spec, resolution), nn.Linear(spec.channels[-1], width)


VISION_TOWERS: Registry[Callable[..., tuple[nn.Module, nn.Module]]] = Registry("vision encoder kind")
VISION_TOWERS.add("siglip", build_siglip)
VISION_TOWERS.add("conv", build_conv)
