"""The one records class: what every trainer keeps of its members' diagnostics besides its update.

Per member: the sums of its loss terms over the last 10 % of training (the row's ``loss_*`` columns) and its
learning curve, CURVE_POINTS points each the mean over the updates just before it (a tenth of the interval
between points), every PROBE_EVERY-th point (and the last) with the cheap probe's ``probe_*`` metrics. The
reference Trainer keeps one member's, a packed trainer K; the sums are float64 whatever the update's
precision, so a value recorded in float32 adds exactly as a Python float would.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

import torch

from asp_dist.spec import CellSpec
from asp_dist.training.methods import LossWeights, lambda_factor
from asp_dist.training.row import LOSS_TERMS

CURVE_POINTS = 50  # learning-curve points per cell
PROBE_EVERY = 5  # every 5th point (10 per cell) also evaluates against the base, cheaply
TERMS = LOSS_TERMS + ("disc_acc_real", "disc_acc_fake", "d_fake")  # what a member may record per update
COL = {name: i for i, name in enumerate(TERMS)}


def member_terms(weights: LossWeights, n_paired: int) -> tuple[str, ...]:
    """The loss and discriminator columns a member records (its terms with a weight), in TERMS' order."""
    return (("self_play",) if weights.needs_self_play else ()) + (("paired",) if n_paired else ()) \
        + (("unpaired", "disc", "disc_acc_real", "disc_acc_fake", "d_fake") if weights.needs_adversary else ()) \
        + ("total",)


class Member(Protocol):
    """What Records reads and sets on a member when a curve point closes."""

    spec: CellSpec
    weights: LossWeights
    probe: Callable[[int], dict[str, float]] | None
    curve: list[dict[str, float]]

    @property
    def failed(self) -> bool: ...


class Records:
    """The records of members that record `terms` (one tuple per member) over `train_steps` updates."""

    def __init__(self, terms: Sequence[tuple[str, ...]], train_steps: int):
        self.terms = [tuple(t) for t in terms]
        self.present = torch.tensor([[name in t for name in TERMS] for t in self.terms])
        self.train_steps = train_steps
        self.window_start = int(0.9 * train_steps)
        self.curve_every = max(1, train_steps // CURVE_POINTS)
        self.curve_window = max(1, self.curve_every // 10)
        self.loss_sums = torch.zeros(len(self.terms), len(LOSS_TERMS), dtype=torch.float64)
        self.loss_count = 0
        self.curve_sums = torch.zeros(len(self.terms), len(TERMS), dtype=torch.float64)
        self.curve_count = 0

    def in_curve_window(self, step: int) -> bool:
        """Whether update `step` is among the last curve_window before a curve point."""
        return (-step - 1) % self.curve_every < self.curve_window

    def recording(self, step: int) -> bool:
        """Whether update `step`'s values are recorded (final window or a curve window)."""
        return step >= self.window_start or self.in_curve_window(step)

    def add(self, step: int, values: torch.Tensor) -> None:
        """Update `step`'s values: float64, one row per member, one column per TERMS name, 0 where a member
        does not record the term."""
        if step >= self.window_start:
            self.loss_sums += values[:, :len(LOSS_TERMS)]
            self.loss_count += 1
        if self.in_curve_window(step):
            self.curve_sums += values
            self.curve_count += 1

    def finish_point(self, step: int, members: Sequence[Member]) -> None:
        """After update `step`, close the curve point that ends there (if one does), for every member
        still training."""
        if step % self.curve_every and step != self.train_steps:
            return
        n, sums = self.curve_count, self.curve_sums.tolist()
        for i, m in enumerate(members):
            if m.failed:
                continue
            # λ1 of the update just before the point.
            point = {"step": float(step), "lambda_unpaired_now": m.weights.unpaired * lambda_factor(m.spec, step - 1)}
            if n:
                point.update({(f"loss_{k}" if k in LOSS_TERMS else k): sums[i][COL[k]] / n for k in self.terms[i]})
            index = len(m.curve)
            if m.probe is not None and (index % PROBE_EVERY == PROBE_EVERY - 1 or step == self.train_steps):
                point.update({f"probe_{k}": float(v) for k, v in m.probe(step).items()})
            m.curve.append(point)
        self.curve_sums.zero_()
        self.curve_count = 0

    def loss_columns(self, i: int) -> dict[str, float | None]:
        """Member i's row columns loss_*: the mean of each term it records over the final window."""
        n, terms, sums = self.loss_count, self.terms[i], self.loss_sums[i].tolist()
        return {f"loss_{k}": (sums[c] / n if n and k in terms else None) for c, k in enumerate(LOSS_TERMS)}

    def state(self) -> dict[str, Any]:
        return {"loss_sums": self.loss_sums.clone(), "loss_count": self.loss_count,
                "curve_sums": self.curve_sums.clone(), "curve_count": self.curve_count}

    def load(self, state: dict[str, Any]) -> None:
        self.loss_sums.copy_(state["loss_sums"])
        self.curve_sums.copy_(state["curve_sums"])
        self.loss_count, self.curve_count = state["loss_count"], state["curve_count"]

    def load_single(self, loss_sums: dict[str, float], curve_sums: dict[str, float]) -> None:
        """A one-member state of the reference Trainer from before this class (sums by name, "_count")."""
        self.loss_sums.zero_()
        self.curve_sums.zero_()
        for name, value in loss_sums.items():
            if name != "_count":
                self.loss_sums[0, LOSS_TERMS.index(name)] = value
        for name, value in curve_sums.items():
            if name != "_count":
                self.curve_sums[0, COL[name]] = value
        self.loss_count, self.curve_count = int(loss_sums.get("_count", 0)), int(curve_sums.get("_count", 0))
