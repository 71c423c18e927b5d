"""Packed trainers: K cells of one domain that share tensor shapes, trained as ONE batched model
(parameters stacked on a leading member dimension, one batched update and one Adam step for all).

Each member keeps its own loss weights, data, initial weights and random streams, so that its
result is the one its single-cell run gives (up to float rounding) whatever its pack-mates are.

A domain has a packed trainer when a module is registered for it in PACKED below. Such a module
has three functions, which this package dispatches to by the cells' domain:

    supports(spec) -> bool          whether the cell can train in a pack (its knob values are implemented)
    pack_key(spec) -> tuple         cells with equal keys can share a pack (tensor shapes, training length)
    run_pack(specs, *, bases=None, curves=False, progress=None[, checkpoint=None, restore=None,
             checkpoint_every_s=30.0]) -> list of results with .spec, .row, .curve, .error (one per spec)

The checkpoint arguments are optional: a module whose run_pack does not take them trains without
checkpoints (a pack restarted after a crash then starts over). The sweep (asp_dist.sweep.packing,
asp_dist.sweep.tune) uses only the functions of this package, never a domain's module directly.
"""

from __future__ import annotations

import importlib
import inspect
from types import ModuleType
from typing import Any, Callable, Sequence

from asp_dist.domains.contract import ProgressFn
from asp_dist.spec import CellSpec
from asp_dist.training.packed.particles import PackedParticleTrainer, PackedResult

# domain -> module with supports / pack_key / run_pack. One line registers a domain's packed trainer.
PACKED: dict[str, str] = {
    "particles": "asp_dist.training.packed.particles",
}

CHECKPOINT_ARGS = ("checkpoint", "restore", "checkpoint_every_s")


def packed_module(domain: str) -> ModuleType | None:
    """The packed-trainer module of a domain, or None when the domain has none."""
    name = PACKED.get(domain)
    return importlib.import_module(name) if name is not None else None


def supports(spec: CellSpec) -> bool:
    """Whether `spec` can train in a pack: its domain has a packed trainer that implements its knobs."""
    module = packed_module(spec.domain)
    return module is not None and bool(module.supports(spec))


def pack_key(spec: CellSpec) -> tuple:
    """Cells with equal keys can share a pack (the domain first: packs never mix domains)."""
    module = packed_module(spec.domain)
    if module is None:
        raise ValueError(f"domain {spec.domain!r} has no packed trainer")
    return (spec.domain, *module.pack_key(spec))


def checkpoints(domain: str) -> bool:
    """Whether the domain's run_pack can checkpoint and restore a pack."""
    module = packed_module(domain)
    if module is None:
        return False
    params = inspect.signature(module.run_pack).parameters
    return all(name in params for name in CHECKPOINT_ARGS)


def run_pack(specs: Sequence[CellSpec], *, bases: dict | None = None, curves: bool = False,
             progress: ProgressFn | None = None, checkpoint: Callable[[dict], None] | None = None,
             restore: dict | None = None, checkpoint_every_s: float = 30.0) -> list[Any]:
    """Train `specs` (cells of one domain, one pack_key) as one pack with their domain's packed trainer.

    Returns one result per spec, in order (``.spec``, ``.row`` as run_cell's, ``.curve``, ``.error``).
    checkpoint / restore / checkpoint_every_s as run_cell's; ignored (no checkpoints, restore=None
    refused) by a domain whose packed trainer cannot checkpoint."""
    specs = list(specs)
    if not specs:
        return []
    domains = sorted({s.domain for s in specs})
    if len(domains) > 1:
        raise ValueError(f"a pack holds cells of one domain, got {', '.join(domains)}")
    module = packed_module(domains[0])
    if module is None:
        raise ValueError(f"domain {domains[0]!r} has no packed trainer")
    kwargs: dict[str, Any] = dict(bases=bases, curves=curves, progress=progress)
    if checkpoints(domains[0]):
        kwargs.update(checkpoint=checkpoint, restore=restore, checkpoint_every_s=checkpoint_every_s)
    elif restore is not None:
        raise ValueError(f"the packed trainer of {domains[0]} cannot restore a checkpoint")
    return module.run_pack(specs, **kwargs)


__all__ = ["PACKED", "PackedParticleTrainer", "PackedResult", "checkpoints", "pack_key", "packed_module",
           "run_pack", "supports"]
