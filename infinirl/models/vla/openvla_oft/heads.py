"""OFT's extra modules, saved beside the VLA folder as ``<name>--<step>_checkpoint.pt``.

* :class:`L1RegressionHead` (``action_head--*``): an MLP-ResNet (pre-LayerNorm blocks, ReLU) from
  the ``action_dim`` hidden states of each action's tokens, concatenated, to that action:
  ``[B, chunk * action_dim, H] -> [B, chunk, action_dim]`` (normalised units).
* :class:`ProprioProjector` (``proprio_projector--*``): ``fc1-GELU-fc2`` from the normalised proprio
  to one token appended after the image patches.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["L1RegressionHead", "ProprioProjector", "ResidualBlock"]


class ResidualBlock(nn.Module):
    """``x + ReLU(Linear(LayerNorm(x)))``."""

    def __init__(self, dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.linear = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + torch.relu(self.linear(self.norm(x)))


class L1RegressionHead(nn.Module):
    def __init__(self, llm_dim: int, action_dim: int, num_blocks: int = 2):
        super().__init__()
        self.action_dim = action_dim
        input_dim = llm_dim * action_dim
        self.layer_norm1 = nn.LayerNorm(input_dim)
        self.fc1 = nn.Linear(input_dim, llm_dim)
        self.blocks = nn.ModuleList(ResidualBlock(llm_dim) for _ in range(num_blocks))
        self.layer_norm2 = nn.LayerNorm(llm_dim)
        self.fc2 = nn.Linear(llm_dim, action_dim)

    def forward(self, action_hidden: torch.Tensor) -> torch.Tensor:
        batch = action_hidden.shape[0]
        x = action_hidden.reshape(batch, -1, self.action_dim * action_hidden.shape[-1])
        x = torch.relu(self.fc1(self.layer_norm1(x)))
        for block in self.blocks:
            x = block(x)
        return self.fc2(self.layer_norm2(x))


class ProprioProjector(nn.Module):
    def __init__(self, proprio_dim: int, llm_dim: int):
        super().__init__()
        self.fc1 = nn.Linear(proprio_dim, llm_dim)
        self.fc2 = nn.Linear(llm_dim, llm_dim)
        self.act = nn.GELU()

    def forward(self, proprio: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(proprio)))
