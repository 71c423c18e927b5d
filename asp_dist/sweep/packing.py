"""How a sweep groups its cells into the units a Tune trial runs: one cell, or a pack of cells
trained together as one batched model (asp_dist.training.engines).

    --pack cell     one cell per Tune trial (the default)
    --pack trial    the packable cells of one (domain, root seed, trial) that share a pack_key
    --pack method   the packable cells of one (domain, method) that share a pack_key, across trials
    --pack-size N   at most N cells per pack (default DEFAULT_PACK_SIZE): a larger group is split
                    into ceil(n / N) packs of near-equal size, its cells sorted by cell id

A packed member's row is reproducible bit for bit only for a fixed pack composition and shape
(pack-mates change rounding at ~1e-7, which over a whole cell may flip a sampled action), so
the packs are a deterministic function of the grid and the packing (mode, size) alone, never of
which cells are already done: a resumed sweep rebuilds exactly the same packs, trains a pack
that has some rows again as a whole, and writes only the members without a row. The packing is
stored in the sweep's manifest when the sweep starts and cannot change afterwards.

A packed sweep hands its workers the bases missing from its cache first, as units of their own (bases_first),
then the packs, spread over their bases (schedule).

Cells that cannot be packed (a domain without a packed trainer, knob values its packed trainer
does not implement, a packed trainer kept out of sweeps because it is slower than the single-cell
path: the VAE's, asp_dist.training.engines.sweep_packs) and groups of a single cell run one cell per
trial, as without --pack.
No Ray import.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from asp_dist.errors import SweepError
from asp_dist.hashing import stable_hash
from asp_dist.results import store
from asp_dist.results.location import AnyPath
from asp_dist.spec import CellSpec

PACK_MODES = ("cell", "trial", "method")
DEFAULT_PACK_MODE = "cell"
# One trial of the paper's particle grid (7 paired counts x 3 methods): --pack trial packs a whole
# trial of paper-particles, and --pack method splits its 210 cells per method into 10 packs.
DEFAULT_PACK_SIZE = 21
MANIFEST_KEY = "packing"


@dataclass(frozen=True)
class Packing:
    """How a sweep's cells are grouped: mode (PACK_MODES) and the largest pack (None for "cell")."""

    mode: str = DEFAULT_PACK_MODE
    size: int | None = None

    @property
    def packed(self) -> bool:
        return self.mode != "cell"

    def to_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "size": self.size}

    def describe(self) -> str:
        return "one cell per trial" if not self.packed else f"--pack {self.mode} --pack-size {self.size}"


def check_packing(mode: str | None, size: int | None) -> None:
    """The --pack and --pack-size flags as given (None: not given), refused in one line before anything runs."""
    if mode is not None and mode not in PACK_MODES:
        raise SweepError(f"--pack {mode!r}: choose one of {', '.join(PACK_MODES)}")
    if size is not None:
        if isinstance(size, bool) or not isinstance(size, int):
            raise SweepError(f"--pack-size must be an integer, got {size!r}")
        if size < 1:
            raise SweepError(f"--pack-size must be >= 1, got {size}")
        if mode == "cell":
            raise SweepError("--pack-size needs --pack trial or --pack method (--pack cell runs one cell per trial)")


def stored_packing(manifest: dict[str, Any] | None) -> Packing | None:
    """The packing a sweep was started with (a manifest written before packing existed: one cell per
    trial); None for a sweep that has no manifest yet."""
    if manifest is None:
        return None
    raw = manifest.get(MANIFEST_KEY)
    if raw is None:
        return Packing()
    ok = isinstance(raw, dict) and raw.get("mode") in PACK_MODES and (
        raw.get("size") is None if raw.get("mode") == "cell"
        else isinstance(raw.get("size"), int) and not isinstance(raw.get("size"), bool) and raw["size"] >= 1)
    if not ok:
        raise SweepError(f"sweep {manifest.get('name')!r}: its manifest's packing {raw!r} cannot be read; "
                         f"start a new sweep name")
    return Packing(raw["mode"], raw.get("size"))


def resolve_packing(mode: str | None, size: int | None, manifest: dict[str, Any] | None) -> Packing:
    """The packing of a run (mode, size: the flags, None where not given).

    A new sweep's comes from the flags (default: one cell per trial; packs of at most DEFAULT_PACK_SIZE).
    An existing sweep keeps the packing it was started with: leaving the flags out continues it, and flags
    that ask for another packing are refused (its rows reproduce only for a fixed packing)."""
    check_packing(mode, size)
    stored = stored_packing(manifest)
    effective = mode or (stored.mode if stored is not None else DEFAULT_PACK_MODE)
    if effective == "cell":
        if size is not None:
            raise SweepError("--pack-size needs --pack trial or --pack method"
                             + (f"; sweep {manifest.get('name')!r} runs one cell per trial" if stored else ""))
        wanted = Packing()
    else:
        kept = stored.size if stored is not None and stored.mode == effective else None
        wanted = Packing(effective, size or kept or DEFAULT_PACK_SIZE)
    if stored is not None and wanted != stored:
        raise SweepError(f"sweep {manifest.get('name')!r} was started with {stored.describe()}, not "
                         f"{wanted.describe()}: rows reproduce only for a fixed packing; leave out --pack and "
                         f"--pack-size to continue it, or use another --name")
    return wanted


@dataclass(frozen=True)
class Unit:
    """What one Tune trial runs: one cell (pack_id None), or the cells of one pack trained together, or (base_only)
    no cell: the base of its one spec, trained into the sweep's cache (bases_first)."""

    specs: tuple[CellSpec, ...]
    pack_id: str | None = None
    base_only: bool = False

    @property
    def cell_ids(self) -> list[str]:
        return [] if self.base_only else [s.cell_id for s in self.specs]

    @property
    def name(self) -> str:
        """The Tune trial's name and directory: the cell id, the pack id made a directory name, or base_<key>."""
        if self.base_only:
            return f"base_{self.specs[0].base_key}"
        return self.specs[0].cell_id if self.pack_id is None else "pack_" + self.pack_id.replace("/", "_")


def _group(spec: CellSpec, mode: str) -> tuple[tuple, str]:
    """The group a packable cell belongs to under `mode` and the group's readable label."""
    from asp_dist.training.engines import pack_key

    key = pack_key(spec)
    if mode == "trial":
        return (spec.domain, spec.trial, spec.root_seed, key), f"{spec.domain}/trial-{spec.trial}"
    return (spec.domain, spec.method, key), f"{spec.domain}/{spec.method}"


def make_units(specs: Sequence[CellSpec], packing: Packing) -> list[Unit]:
    """The sweep's cells as Tune trials: a deterministic function of the cells and the packing only.

    Packs are named ``<domain>/<trial-T | method>/<hash>/<i>of<n>-k<members>``, the hash that of what
    the label leaves out (the pack_key, and the root seed for trial packs), so that groups of one label
    with other shapes or seeds get other names. Units come in the order of their first cell in `specs`
    (the grid's base-friendly order)."""
    specs = [s.resolved() for s in specs]
    if not packing.packed:
        return [Unit((s,)) for s in specs]
    from asp_dist.training.engines import sweep_packs

    groups: dict[tuple, tuple[str, list[CellSpec]]] = {}
    first: dict[str, int] = {s.cell_id: i for i, s in enumerate(specs)}
    unit_at: dict[int, Unit] = {}
    for i, spec in enumerate(specs):
        if not sweep_packs(spec):
            unit_at[i] = Unit((spec,))
            continue
        key, label = _group(spec, packing.mode)
        groups.setdefault(key, (label, []))[1].append(spec)
    for key, (label, members) in groups.items():
        members = sorted(members, key=lambda s: s.cell_id)
        if len(members) == 1:
            unit_at[first[members[0].cell_id]] = Unit((members[0],))
            continue
        size = packing.size or DEFAULT_PACK_SIZE
        n_packs = math.ceil(len(members) / size)
        digest = stable_hash([str(part) for part in key[2:]])[:6]  # what the label does not say
        for p in range(n_packs):
            chunk = members[p * len(members) // n_packs:(p + 1) * len(members) // n_packs]
            pack_id = f"{label}/{digest}/{p + 1}of{n_packs}-k{len(chunk)}"
            unit = Unit(tuple(chunk), pack_id) if len(chunk) > 1 else Unit(tuple(chunk))
            unit_at[min(first[s.cell_id] for s in chunk)] = unit
    return [unit_at[i] for i in sorted(unit_at)]


def spread_bases(units: Sequence[Unit]) -> list[Unit]:
    """`units` in the order a sweep hands them to its workers: the first unit of every base, then the second of
    every base, and so on (each round in the given order). In the grid's order the units of one trial are
    adjacent, so two workers take two units of one trial and the second waits on the base lock while the first
    trains the base (minutes for a base that needs its retries); spread, concurrent units need distinct bases
    and a unit that comes back to a base finds it cached. Only the order changes: the units, their packs and
    their rows are the same."""
    rank: dict[str, int] = {}
    keyed = []
    for position, unit in enumerate(units):
        base = unit.specs[0].base_key
        keyed.append((rank.get(base, 0), position, unit))
        rank[base] = rank.get(base, 0) + 1
    return [unit for _, _, unit in sorted(keyed, key=lambda k: k[:2])]


def bases_first(units: Sequence[Unit], settled: Callable[[str], bool]) -> list[Unit]:
    """`units` after one base-only unit per base they need that is not `settled` (stored, or remembered as
    rejected, in the sweep's cache), in the order the units first need them.

    A pack of one method spans many trials, and so many bases: trained inside the pack, they are trained one
    after another by the pack's one worker while the other workers wait on their locks (the particle grid's
    method packs saved 27 % of training but 5 % of the span: docs/performance.md). As units of their own, Tune
    hands them out first, one per free worker, and the packs start on cached bases. Rows are unchanged: a base
    is the same whoever trains it."""
    missing: dict[str, CellSpec] = {}
    for unit in units:
        for spec in unit.specs:
            if spec.base_key not in missing and not settled(spec.base_key):
                missing[spec.base_key] = spec
    return [Unit((spec,), base_only=True) for spec in missing.values()] + list(units)


def schedule(units: Sequence[Unit], packing: Packing, sweep_dir: AnyPath) -> list[Unit]:
    """The order a sweep hands `units` (those with a cell still to write) to its workers: spread over their bases
    (spread_bases), and in a packed sweep after the bases missing from the sweep's cache (bases_first)."""
    units = spread_bases(units)
    if not packing.packed:
        return units
    bases = store.bases_dir(sweep_dir)
    return bases_first(units, lambda key: store.base_path(bases, key).exists()
                       or store.rejected_base_path(bases, key).exists())


def describe_units(units: Sequence[Unit]) -> str:
    """E.g. "4 packs of 6-21 cells + 3 single cells"."""
    packs = [len(u.specs) for u in units if u.pack_id is not None]
    singles = sum(1 for u in units if u.pack_id is None)
    if not packs:
        return f"{singles} single cell(s)"
    sizes = f"{min(packs)}" if min(packs) == max(packs) else f"{min(packs)}-{max(packs)}"
    return f"{len(packs)} pack(s) of {sizes} cells + {singles} single cell(s)"
