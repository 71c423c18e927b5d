"""Discriminators (one per convention channel) and the two adversarial losses.

The discriminator is trained with binary cross-entropy to tell unpaired base outputs U
("real", label 1) from the new agents' outputs ("fake", label 0). The model's term L_u is
the paper's negative BCE of the discriminator on the fake outputs, -BCE(D(fake), 0) =
log(1 - D(fake)); the non-saturating alternative -log D(fake) is offered as an option.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.nn import init_mlp, seeded


class Discriminator(nn.Module):
    def __init__(self, in_dim: int, hidden: int, layers: int):
        super().__init__()
        self.net = init_mlp([in_dim] + [hidden] * layers + [1], activation=nn.LeakyReLU)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x).squeeze(-1)  # logits


def disc_diagnostics(real_logits: torch.Tensor, fake_logits: torch.Tensor) -> dict[str, float]:
    """What the learning curves record of a discriminator: accuracy on each side and mean D(fake)."""
    return {"disc_acc_real": float((real_logits > 0).float().mean()),
            "disc_acc_fake": float((fake_logits < 0).float().mean()),
            "d_fake": float(torch.sigmoid(fake_logits).mean())}


def model_adversarial_loss(disc: Discriminator, fake: torch.Tensor, kind: str) -> torch.Tensor:
    logits = disc(fake)
    if kind == "neg_bce":
        return -F.binary_cross_entropy_with_logits(logits, torch.zeros_like(logits))
    if kind == "non_saturating":
        return F.binary_cross_entropy_with_logits(logits, torch.ones_like(logits))
    raise ValueError(f"unknown adversary loss {kind!r}")


class Adversaries(nn.Module):
    """One discriminator and optimiser per channel; updated once per training step."""

    def __init__(self, channel_dims: dict[str, int], hidden: int, layers: int, lr: float, seed: int,
                 make_optimizer: Callable = torch.optim.Adam):
        super().__init__()
        self.discs = nn.ModuleDict({
            ch: seeded(seed + i, lambda d=dim: Discriminator(d, hidden, layers))
            for i, (ch, dim) in enumerate(sorted(channel_dims.items()))
        })
        self.optims = {ch: make_optimizer(d.parameters(), lr=lr) for ch, d in self.discs.items()}

    def step(self, real: dict[str, torch.Tensor], fake: dict[str, torch.Tensor],
             diagnostics: dict[str, float] | None = None) -> float:
        """One BCE update of every discriminator; returns the mean discriminator loss. With
        `diagnostics`, also adds (channel means, before the update) its accuracy on real and on
        fake samples and its mean D(fake)."""
        total = 0.0
        for ch, disc in self.discs.items():
            opt = self.optims[ch]
            opt.zero_grad(set_to_none=True)
            real_logits, fake_logits = disc(real[ch]), disc(fake[ch].detach())
            loss = (F.binary_cross_entropy_with_logits(real_logits, torch.ones_like(real_logits))
                    + F.binary_cross_entropy_with_logits(fake_logits, torch.zeros_like(fake_logits)))
            loss.backward()
            opt.step()
            total += float(loss.detach())
            if diagnostics is not None:
                for name, value in disc_diagnostics(real_logits.detach(), fake_logits.detach()).items():
                    diagnostics[name] = diagnostics.get(name, 0.0) + value / len(self.discs)
        return total / max(len(self.discs), 1)

    def model_loss(self, fake: dict[str, torch.Tensor], kind: str) -> torch.Tensor:
        """L_u summed over channels. Gradients land in the discriminators too; they are
        cleared by each discriminator's zero_grad before its own next update."""
        return sum(model_adversarial_loss(disc, fake[ch], kind) for ch, disc in self.discs.items())

    def full_state(self) -> dict:
        return {"params": self.state_dict(), "optims": {ch: o.state_dict() for ch, o in self.optims.items()}}

    def load_full_state(self, state: dict) -> None:
        self.load_state_dict(state["params"])
        for ch, o in self.optims.items():
            o.load_state_dict(state["optims"][ch])
