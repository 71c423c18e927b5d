"""Which trainer trains a cell or a pack: one registry shape for every engine.

A trainer is a class that states its capabilities as attributes (as BenchMARL's algorithm classes do),
so that choosing one is reading attributes, not branching on domains:

    engine      str: names the format of its state_dict(); a checkpoint of another engine is not
                restored (the cell starts over)
    packs       trains K cells of one domain as one batched model (a ``--pack`` sweep's packs, run_pack)
    lone        trains a single cell (run_cell, a sweep's single cells)
    in_sweeps   a ``--pack`` sweep puts the cells it supports in its packs; False for a packed trainer
                measured slower than the lone path (it stays registered, tested and benchmarked)
    supports(spec) -> bool    it implements every knob value of `spec`
    implements  (a trainer that re-derives the domain's update, such as a packed one) every knob of its
                domain -> the values it implements (asp_dist.knobs: ANY, BASE_ONLY or a tuple of values);
                None (the reference Trainer and its subclasses) where the update is the domain's own
                game functions, which implement every value
    pack_key(spec) -> tuple   (packs only) cells with equal keys can share a pack: tensor shapes, length
    build(specs, paired, unpaired, agents)   the trainer of those members (one for a lone trainer), with
                the interface the cell pipeline drives (asp_dist.training.pipeline.UnitTrainer)

A domain lists its own trainers, fastest first, in ``Domain.trainers`` (a built-in domain in its package's
``trainers`` module, beside its game); the reference Trainer (autograd, asp_dist.training.trainer) closes
every list: it trains any cell alone, and the fast trainers are tested against it. A cell trains on the first
trainer that trains lone cells and supports it; a pack on the first that packs and supports every member.
The sweep (asp_dist.sweep.packing, asp_dist.sweep.trial) and run_cell ask only this module.

A trainer whose `implements` leaves out a knob of its domain (a knob added to the domain's game but not to
the trainer) is refused when its domain's trainers are first read: one warning, and its cells train on the
next trainer. A cell whose knob values a faster trainer does not implement trains on the next that does,
with one log line saying why.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable, Sequence

from asp_dist.core.contract import ProgressFn
from asp_dist.core.registry import get_domain
from asp_dist.knobs import implements_problems
from asp_dist.spec import CellSpec
from asp_dist.training.pipeline import CellResult, one_domain, run_unit
from asp_dist.training.trainer import Trainer

REFERENCE = Trainer


log = logging.getLogger(__name__)
_REFUSED: dict[tuple, list[str]] = {}  # (domain, its knobs, trainer) -> why refused; warned once per process


def trainer_problems(trainer: type, domain: str) -> list[str]:
    """Why `trainer` cannot be one of `domain`'s trainers: its `implements` does not cover every knob of the
    domain (or names a field that does not exist); empty for a trainer without `implements` (the reference
    and its subclasses, which run the domain's own game functions)."""
    implements = getattr(trainer, "implements", None)
    if implements is None:
        return []
    problems = implements_problems(implements, get_domain(domain).knobs, {f.name for f in dataclasses.fields(CellSpec)})
    if getattr(trainer, "domain", domain) != domain:
        problems.append(f"it trains {trainer.domain!r} cells, not {domain!r} ones")
    return problems


def trainers_of(domain: str) -> tuple[type, ...]:
    """Every trainer of `domain`, in the order they are tried: the domain's own that pass trainer_problems
    (a refused one is warned about once), then the reference."""
    accepted, card = [], get_domain(domain)
    knobs = tuple(k.name for k in card.knobs)
    for trainer in card.trainers:
        key = (domain, knobs, trainer)
        if key not in _REFUSED:
            _REFUSED[key] = trainer_problems(trainer, domain)
            if _REFUSED[key]:
                log.warning("%s: trainer %s refused (its cells train on the next trainer): %s", domain,
                            trainer.__name__, "; ".join(_REFUSED[key]))
        if not _REFUSED[key]:
            accepted.append(trainer)
    return (*accepted, REFERENCE)


def unsupported(trainer: type, spec: CellSpec) -> list[str]:
    """What of `spec` `trainer` does not implement (empty when it supports it)."""
    if trainer.supports(spec):
        return []
    why = getattr(trainer, "unsupported", None)
    return (why(spec) if why is not None else []) or ["this cell"]


def lone_trainer(spec: CellSpec) -> type:
    """The trainer of `spec` as a single cell: the first of its domain's that trains lone cells and
    supports it (the reference Trainer supports every cell). Where a faster lone trainer was passed over,
    one log line says which knob values it does not implement."""
    passed = []
    for trainer in trainers_of(spec.domain):
        if not trainer.lone:
            continue
        missing = unsupported(trainer, spec)
        if not missing:
            if passed:
                log.info("%s trains on %s: %s", spec.cell_id, trainer.__name__, "; ".join(passed))
            return trainer
        passed.append(f"{trainer.__name__} does not implement {', '.join(missing)}")
    raise AssertionError("the reference Trainer trains every cell")


def pack_trainer(spec: CellSpec) -> type | None:
    """The trainer of packs that `spec` can join, or None where its domain has none that supports it."""
    return next((t for t in trainers_of(spec.domain) if t.packs and t.supports(spec)), None)


def supports(spec: CellSpec) -> bool:
    """Whether `spec` can train in a pack: its domain has a packed trainer that implements its knobs."""
    return pack_trainer(spec) is not None


def sweep_packs(spec: CellSpec) -> bool:
    """Whether a sweep run with --pack puts `spec` in a pack: a packed trainer supports it and is meant
    for sweeps (``in_sweeps``; the VAE's is not: docs/performance.md)."""
    trainer = pack_trainer(spec)
    return trainer is not None and trainer.in_sweeps


def pack_key(spec: CellSpec) -> tuple:
    """Cells with equal keys can share a pack (the domain first: packs never mix domains). Pack ids hash it
    (asp_dist.sweep.packing), so it keeps this shape: recorded packs keep their names."""
    trainer = pack_trainer(spec)
    if trainer is None:
        raise ValueError(f"{spec.cell_id}: no packed trainer of domain {spec.domain!r} supports this cell")
    return (spec.domain, *trainer.pack_key(spec))


def run_pack(specs: Sequence[CellSpec], *, bases: dict | None = None, curves: bool = False,
             progress: ProgressFn | None = None, checkpoint: Callable[[dict], None] | None = None,
             restore: dict | None = None, checkpoint_every_s: float = 30.0,
             checkpoint_every_steps: int | None = None) -> list[CellResult]:
    """Train `specs` (cells of one domain that one packed trainer supports) as one pack.

    Returns one CellResult per spec, in order (``.spec``, ``.row`` as run_cell's, ``.curve``, ``.error``);
    the other arguments as asp_dist.training.pipeline.run_unit's."""
    specs = [s.resolved() for s in specs]
    if not specs:
        return []
    domain = one_domain(specs)
    trainer = pack_trainer(specs[0])
    if trainer is None:
        raise ValueError(f"domain {domain!r} has no packed trainer that supports {specs[0].cell_id}")
    return run_unit(trainer, specs, bases=bases, curves=curves, progress=progress, checkpoint=checkpoint,
                    restore=restore, checkpoint_every_s=checkpoint_every_s,
                    checkpoint_every_steps=checkpoint_every_steps)


__all__ = ["REFERENCE", "CellResult", "lone_trainer", "pack_key", "pack_trainer", "run_pack", "supports",
           "sweep_packs", "trainer_problems", "trainers_of", "unsupported"]
