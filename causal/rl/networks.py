"""Building blocks shared by the agents: plain MLPs and the abstraction's input mask."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
from torch import nn

from causal.rl.base import mask_tensor


def mlp(inputs: int, hidden: Sequence[int], outputs: int, activation: type[nn.Module] = nn.ReLU,
        out_gain: float | None = None) -> nn.Sequential:
    """``inputs -> hidden... -> outputs``; with ``out_gain``, orthogonal init (hidden gain sqrt 2)."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(inputs, width), activation()]
        inputs = width
    layers.append(nn.Linear(inputs, outputs))
    if out_gain is not None:
        linears = [m for m in layers if isinstance(m, nn.Linear)]
        for n, layer in enumerate(linears):
            nn.init.orthogonal_(layer.weight, out_gain if n == len(linears) - 1 else math.sqrt(2))
            nn.init.zeros_(layer.bias)
    return nn.Sequential(*layers)


class InputMask(nn.Module):
    """Zeroes the observation dimensions an abstraction drops (all kept when the mask is None)."""

    def __init__(self, obs_dim: int, mask: np.ndarray | Sequence[bool] | None = None) -> None:
        super().__init__()
        self.obs_dim = obs_dim
        self.register_buffer("mask", mask_tensor(mask, obs_dim))

    def set(self, mask: np.ndarray | Sequence[bool] | None) -> None:
        """Replace the mask in place (None switches masking off)."""
        self.mask.copy_(mask_tensor(mask, self.obs_dim))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return obs * self.mask
