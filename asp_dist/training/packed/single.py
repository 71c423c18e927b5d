"""One cell trained as a one-member pack, behind the interface run_cell uses of a Trainer.

A domain whose packed trainer is also its fast single-cell path binds this to its trainer:
``single_cell = partial(single.PackOfOne, MyTrainer)`` (asp_dist.training.packed.PACKED; today the
particle and lever worlds). asp_dist.training.cell.choose_trainer then trains every cell the trainer supports
as a pack of one; the others run on the domain's fast trainer or the reference Trainer. The update is the packed
trainer's, with the member's own generator drawn in the single-cell order; its arithmetic is that
of a pack of one (a pack of other shapes rounds a few kernels differently: rows are reproducible
for a fixed packing, docs/sweeps.md).

What run_cell and train_to_end use: step, train_step(), probe (set before training), curve,
loss_columns(), state_dict() / load_state_dict() (the pack's checkpoint: everything to continue
bit for bit) and `engine`, which names the checkpoint's format. The agents given are re-pointed
into the pack's parameter buffer, so the caller's module holds the trained weights.

A pack freezes a member whose gradient or recorded loss is not finite and carries on; a single cell
has nothing to carry on with, so train_step raises CellDiverged instead (a RuntimeError, as the
autograd path's sampling from a non-finite policy raises): the cell fails rather than report
frozen weights, and the sweep records that once.
"""

from __future__ import annotations

from typing import Any, Callable

import torch

from asp_dist.domains.contract import Tensors
from asp_dist.spec import CellSpec

ENGINE = "pack-of-one"  # prefix of these trainers' checkpoint `engine` (the reference Trainer's: "autograd")


class CellDiverged(RuntimeError):
    """A cell trained alone whose gradient or recorded loss became non-finite. Deterministic: the
    sweep records it as the cell's failure once instead of retrying it (asp_dist.sweep.tune)."""


class PackOfOne:
    """`trainer_class` (a domain's packed trainer) with one member: `spec`, its P, U and fresh agents."""

    def __init__(self, trainer_class: type, spec: CellSpec, agents: torch.nn.Module, paired: Tensors,
                 unpaired: Tensors):
        self.spec, self.agents = spec, agents
        self.pack = trainer_class([spec], [paired], [unpaired], [agents])
        self.member = self.pack.members[0]
        # names the checkpoint's format: the packed trainer whose state it is
        self.engine = f"{ENGINE}/{trainer_class.__name__}"

    @property
    def step(self) -> int:
        return self.pack.step

    @property
    def probe(self) -> Callable[[int], dict[str, float]] | None:
        return self.member.probe

    @probe.setter
    def probe(self, probe: Callable[[int], dict[str, float]] | None) -> None:
        self.member.probe = probe

    @property
    def curve(self) -> list[dict[str, float]]:
        return self.member.curve

    def train_step(self) -> None:
        self.pack.train_step()
        if self.member.failed:
            raise CellDiverged(f"cell {self.spec.cell_id}: {self.member.error}")

    def loss_columns(self) -> dict[str, float | None]:
        return self.pack.loss_columns(0)

    def state_dict(self) -> dict[str, Any]:
        return self.pack.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pack.load_state_dict(state)
