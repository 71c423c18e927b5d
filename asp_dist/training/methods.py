"""PC, OSP and ASP (and any registered method, asp_dist.method_registry) as weights on one loss:
L = w_sp·L_sp + λ0·L_p + λ1·L_u.

PC   (policy cloning):            w_sp = 0, λ1 = 0  — paired data only, no self-play.
OSP  (observationally augmented   w_sp = 1, λ1 = 0  — self-play and paired loss, interleaved
      self-play):                                     in every update.
ASP  (adversarial self-play):     w_sp = 1, λ1 > 0  — OSP plus adversaries on unpaired data.

A term whose weight is zero is not computed at all (PC never rolls out self-play), which
keeps the composition exact: with λ0 = λ1 = 0 the loss *is* L_sp.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from asp_dist.method_registry import get_method
from asp_dist.spec import CellSpec


@dataclass(frozen=True)
class LossWeights:
    self_play: float
    paired: float
    unpaired: float

    @property
    def needs_self_play(self) -> bool:
        return self.self_play != 0.0

    @property
    def needs_adversary(self) -> bool:
        return self.unpaired != 0.0


def method_weights(spec: CellSpec) -> LossWeights:
    """The weights of the registered method's terms (asp_dist.method_registry.Method) at the spec's λ0 and λ1."""
    spec = spec.resolved()
    method = get_method(spec.method)
    return LossWeights(self_play=1.0 if method.self_play else 0.0,
                       paired=float(spec.lambda_paired) if method.paired and spec.paired > 0 else 0.0,
                       unpaired=float(spec.lambda_unpaired) if method.adversarial else 0.0)


def compose_loss(weights: LossWeights, self_play: torch.Tensor | None, paired: torch.Tensor | None,
                 unpaired: torch.Tensor | None) -> torch.Tensor:
    """The weighted sum; a term may be None exactly when its weight is zero."""
    total: torch.Tensor | None = None
    for weight, term, name in ((weights.self_play, self_play, "self-play"),
                               (weights.paired, paired, "paired"),
                               (weights.unpaired, unpaired, "unpaired")):
        if weight == 0.0:
            continue
        if term is None:
            raise ValueError(f"the {name} term has weight {weight} but was not computed")
        total = weight * term if total is None else total + weight * term
    if total is None:
        # Nothing to learn (e.g. PC with zero paired examples): a zero loss with no gradient.
        return torch.zeros(())
    return total


def lambda_factor(spec: CellSpec, step: int) -> float:
    """λ1's multiplier at update `step` under spec.lambda_unpaired_schedule: constant 1; warmup
    rises linearly from 0 to 1 over the first lambda_schedule_frac of the updates; anneal falls
    linearly from 1 to 0 over them (the remaining updates have no adversarial term)."""
    if spec.lambda_unpaired_schedule == "constant":
        return 1.0
    ramp = min(1.0, step / max(1.0, spec.lambda_schedule_frac * spec.train_steps))
    return ramp if spec.lambda_unpaired_schedule == "warmup" else 1.0 - ramp
