"""Packed trainers: K cells of one domain that share tensor shapes, trained as ONE batched model
(parameters stacked on a leading member dimension, one batched update and one Adam step for all).

Each member keeps its own loss weights, data, initial weights and random streams, so that its
result is the one its single-cell run gives up to float rounding, whatever its pack-mates are
(bit for bit for a fixed packing; see docs/sweeps.md, "Packed training").

    stacked.py     what the packed trainers share: StackedParams (stacked parameters, one fused Adam
                   step), column, retain_freed_memory (the allocator setting lever packs need)
    driver.py      run_pack for any domain: bases, data, the packed trainer, checkpoints, evaluation,
                   rows; PackedResult
    single.py      PackOfOne: one cell as a one-member pack, with the interface run_cell uses
    particles.py   PackedParticleTrainer (the particle update, batched, hand-derived gradients)
    levers.py      PackedLeverTrainer (the CommNet lever update, batched, hand-derived gradients)
    vae.py         PackedVAETrainer (the one-pass VAE update, batched matmuls, autograd over the
                   stacked parameters)

A domain has a packed trainer when a module is registered for it in PACKED below. Such a module
has three functions, which this package dispatches to by the cells' domain:

    supports(spec) -> bool          whether the cell can train in a pack (its knob values are implemented)
    pack_key(spec) -> tuple         cells with equal keys can share a pack (tensor shapes, training length)
    run_pack(specs, *, bases=None, curves=False, progress=None, checkpoint=None, restore=None,
             checkpoint_every_s=30.0) -> list of PackedResult (.spec, .row, .curve, .error), one per spec

It may set ``IN_SWEEPS = False``: a sweep run with --pack then leaves its cells single
(sweep_packs below), for a packed trainer measured slower than the single-cell path.

Its run_pack is driver.run_pack bound to its trainer, so every registered domain checkpoints and
restores a pack. The sweep (asp_dist.sweep.packing, asp_dist.sweep.tune) uses only the functions
of this package, never a domain's module directly.

A module may also bind ``single_cell = partial(single.PackOfOne, MyTrainer)``: then run_cell trains
each cell of the domain that `supports` accepts as a one-member pack (single_cell_trainer below,
asked by asp_dist.training.cell.choose_trainer); the domain's other cells, and every cell of a domain
without it, run on its fast trainer where asp_dist.training.fast has one, else the reference
Trainer. The particle and lever worlds bind it (a pack of one is faster than the hand-derived
single-cell kernel the particles had, and 3.0× the lever reference: docs/decisions.md,
docs/performance.md); the VAE does not (its single cells run on OnePassVAETrainer,
asp_dist.training.fast.vae).
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Callable, Sequence

import torch

from asp_dist.domains.contract import ProgressFn, Tensors
from asp_dist.spec import CellSpec
from asp_dist.training.packed.driver import PackedResult
from asp_dist.training.packed.single import PackOfOne

# domain -> module with supports / pack_key / run_pack. One line registers a domain's packed trainer.
PACKED: dict[str, str] = {
    "particles": "asp_dist.training.packed.particles",
    "levers": "asp_dist.training.packed.levers",
    "vae": "asp_dist.training.packed.vae",
}


def packed_module(domain: str) -> ModuleType | None:
    """The packed-trainer module of a domain, or None when the domain has none."""
    name = PACKED.get(domain)
    return importlib.import_module(name) if name is not None else None


def supports(spec: CellSpec) -> bool:
    """Whether `spec` can train in a pack: its domain has a packed trainer that implements its knobs."""
    module = packed_module(spec.domain)
    return module is not None and bool(module.supports(spec))


def sweep_packs(spec: CellSpec) -> bool:
    """Whether a sweep run with --pack puts `spec` in a pack: its domain's packed trainer supports it,
    and the module does not set ``IN_SWEEPS = False`` (a packed trainer measured slower than the
    single-cell path on this kind of machine: the VAE's, docs/performance.md). Such a trainer stays
    registered, tested and benchmarked, and run_pack can be called directly."""
    return supports(spec) and bool(getattr(packed_module(spec.domain), "IN_SWEEPS", True))


def single_cell_trainer(spec: CellSpec, agents: torch.nn.Module, paired: Tensors,
                        unpaired: Tensors) -> PackOfOne | None:
    """The trainer of one cell as a one-member pack, where its domain trains single cells so
    (its module binds `single_cell`) and supports the cell's knobs; else None."""
    module = packed_module(spec.domain)
    single = getattr(module, "single_cell", None)
    if single is None or not module.supports(spec):
        return None
    return single(spec, agents, paired, unpaired)


def pack_key(spec: CellSpec) -> tuple:
    """Cells with equal keys can share a pack (the domain first: packs never mix domains)."""
    module = packed_module(spec.domain)
    if module is None:
        raise ValueError(f"domain {spec.domain!r} has no packed trainer")
    return (spec.domain, *module.pack_key(spec))


def run_pack(specs: Sequence[CellSpec], *, bases: dict | None = None, curves: bool = False,
             progress: ProgressFn | None = None, checkpoint: Callable[[dict], None] | None = None,
             restore: dict | None = None, checkpoint_every_s: float = 30.0) -> list[PackedResult]:
    """Train `specs` (cells of one domain, one pack_key) as one pack with their domain's packed trainer.

    Returns one result per spec, in order (``.spec``, ``.row`` as run_cell's, ``.curve``, ``.error``).
    checkpoint / restore / checkpoint_every_s as run_cell's (driver.run_pack)."""
    specs = list(specs)
    if not specs:
        return []
    domains = sorted({s.domain for s in specs})
    if len(domains) > 1:
        raise ValueError(f"a pack holds cells of one domain, got {', '.join(domains)}")
    module = packed_module(domains[0])
    if module is None:
        raise ValueError(f"domain {domains[0]!r} has no packed trainer")
    return module.run_pack(specs, bases=bases, curves=curves, progress=progress, checkpoint=checkpoint,
                           restore=restore, checkpoint_every_s=checkpoint_every_s)


__all__ = ["PACKED", "PackOfOne", "PackedResult", "pack_key", "packed_module", "run_pack", "single_cell_trainer",
           "supports"]
