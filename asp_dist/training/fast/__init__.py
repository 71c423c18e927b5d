"""Fast single-cell trainers: the reference update (asp_dist.training.trainer.Trainer) computed with
fewer or cheaper tensor ops, subclasses of Trainer chosen per cell by
asp_dist.training.cell.choose_trainer where the domain has one and it implements the spec's knobs.
(The particle world's fast single-cell path is a one-member pack instead: asp_dist.training.packed.)

    vae.py   OnePassVAETrainer: self-play and paired rows through each network in one batch
"""

from __future__ import annotations

from asp_dist.spec import CellSpec
from asp_dist.training.fast.vae import OnePassVAETrainer
from asp_dist.training.trainer import Trainer

FAST_TRAINERS: dict[str, type[Trainer]] = {"vae": OnePassVAETrainer}


def fast_trainer(spec: CellSpec) -> type[Trainer] | None:
    """The fast trainer class for `spec`, or None where its domain has none or it lacks a knob value."""
    cls = FAST_TRAINERS.get(spec.domain)
    return cls if cls is not None and cls.supports(spec) else None
