"""Small PyTorch helpers shared by the domains and the adversary."""

from __future__ import annotations

from typing import Callable

import torch
from torch import nn


def init_mlp(sizes: list[int], activation: type[nn.Module] = nn.ReLU, out_activation: nn.Module | None = None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(activation())
    if out_activation is not None:
        layers.append(out_activation)
    return nn.Sequential(*layers)


def seeded(seed: int, build: Callable[[], nn.Module]) -> nn.Module:
    """Build a module with parameters drawn from `seed`, leaving the global RNG untouched."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return build()
