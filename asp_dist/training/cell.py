"""run_cell: one (domain, method, paired, trial) cell end to end, returning one result row.

Pure PyTorch, no Ray: the sweep service wraps this, tests call it directly. Phases:

    base   train (or receive) the base convention, retrying until it meets the domain's bar
    data   sample the paired set P and the unpaired set U from the base
    train  train new agents with the method's loss, L = w_sp·L_sp + λ0·L_p + λ1·L_u
    eval   mixed teams (Eq. 1), both directions, self-play of the new agents and of the base

A cell is the cell pipeline's unit of one (asp_dist.training.pipeline.run_unit) on its lone trainer
(asp_dist.training.engines.lone_trainer: a particle or lever cell whose knobs its domain's packed trainer
implements trains as a one-member pack of it, a VAE cell on its hand-derived trainer (or the one-pass one where
that does not apply), every other cell on the reference Trainer: autograd). The full training state can be checkpointed at any step and restored; a
restored run gives the same row as an uninterrupted one (all randomness flows through saved generators).
"""

from __future__ import annotations

from typing import Any, Callable

from asp_dist.core.contract import ProgressFn
from asp_dist.spec import CellSpec
from asp_dist.training.bases import BaseModel
from asp_dist.training.engines import lone_trainer
from asp_dist.training.pipeline import CellDiverged, run_unit

__all__ = ["CellDiverged", "run_cell"]

Checkpoint = Callable[[dict], None]


def run_cell(spec: CellSpec, *, base: BaseModel | None = None, progress: ProgressFn | None = None,
             checkpoint: Checkpoint | None = None, restore: dict | None = None,
             checkpoint_every_steps: int | None = None, checkpoint_every_s: float = 30.0,
             curve: list[dict[str, float]] | None = None) -> dict[str, Any]:
    """Run one cell and return its result row (a flat dict of scalars and strings).

    base        a trained base to reuse (else trained here, deterministically from the spec)
    progress    progress(phase, done, total, info), called about 100 times during training
    checkpoint  called with the full training state every `checkpoint_every_steps` updates, or
                every `checkpoint_every_s` seconds when no step interval is given
    restore     a state previously passed to `checkpoint`: training continues from it. A state of
                another cell is refused (ValueError); a state of another engine than the one that
                trains this cell now (made by older code) is not restored, and the cell starts over
    curve       a list to fill with the cell's learning curve: ~50 points (dicts with "step",
                loss terms, discriminator accuracy and D(fake), and at ~10 of them "probe_*"
                metrics: the domain's evaluation against the base on a tenth of eval_episodes)

    Raises BaseRejected when no base meets the domain's bar, CellDiverged when training diverged."""
    spec = spec.resolved()
    if base is not None and base.key != spec.base_key:
        raise ValueError(f"base {base.key} was trained for other settings than this cell's ({spec.base_key})")
    (result,) = run_unit(lone_trainer(spec), [spec], bases={spec.base_key: base} if base is not None else None,
                         curves=curve is not None, progress=progress, checkpoint=checkpoint, restore=restore,
                         checkpoint_every_s=checkpoint_every_s, checkpoint_every_steps=checkpoint_every_steps)
    if result.exception is not None:
        raise result.exception
    if curve is not None:
        curve.extend(result.curve)
    return result.row
