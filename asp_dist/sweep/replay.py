"""`asp-dist replay SWEEP CELL_ID`: one finished cell trained again from its stored spec, on this machine, and
its row compared with the stored one, column by column.

The cell is trained as it was: alone on its lone trainer, or, when its row names a pack, with its whole pack
(the units follow from the manifest's grid and packing, as a resumed sweep rebuilds them), because a packed
member's row is reproducible for a fixed packing only (docs/sweeps.md). Its base is the sweep's stored one
when the sweep still has it (bases/), else trained again from its key (deterministic). Nothing is written to
the sweep. No Ray: the cell runs in this process, on one thread as a sweep's worker does.

Bit-identical is the expected answer on the same code, packages and CPU. Otherwise the report names the
columns that differ and what differs in the row's provenance (code revision, package versions, whether the
stored row came from a pack); a CPU with other vector kernels rounds differently
(docs/decisions/0024-numerics-across-cpus.md).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from typing import Any

from asp_dist.errors import SweepError
from asp_dist.results import store
from asp_dist.results.location import AnyPath
from asp_dist.spec import CellSpec
from asp_dist.sweep.base_cache import base_path
from asp_dist.sweep.ledger import check_manifest_shape
from asp_dist.sweep.packing import make_units, stored_packing
from asp_dist.training.artefacts import DamagedArtefact
from asp_dist.training.bases import BaseModel, BaseRejected, base_from_bytes, train_accepted_base
from asp_dist.training.row import VOLATILE_COLUMNS, InvalidRow

# Where and with what a row was made: compared to explain a difference, not as the row's content.
PROVENANCE = ("sweep_id", "ray_node_id", "ray_version", "pack", "asp_dist_version", "torch_version",
              "numpy_version", "python_version", "code_revision")


@dataclass
class Replay:
    """A replayed cell: the stored and the new row, and what differs."""

    cell_id: str
    how: str  # "alone", or "in its pack <id> (K cells)"
    seconds: float
    compared: int  # columns compared
    differs: list[tuple[str, Any, Any]] = field(default_factory=list)  # (column, stored, replayed)
    provenance: list[tuple[str, Any, Any]] = field(default_factory=list)  # (column, stored, now)

    @property
    def identical(self) -> bool:
        return not self.differs

    def text(self) -> str:
        lines = [f"replay of {self.cell_id}: trained {self.how} on this machine in {self.seconds:.1f} s"]
        if self.identical:
            lines.append(f"identical: all {self.compared} non-volatile columns equal the stored row, bit for bit")
        else:
            lines.append(f"{len(self.differs)} of {self.compared} non-volatile columns differ:")
            lines.append("| column | stored | replayed |\n|---|---|---|")
            lines += [f"| {c} | {_show(a)} | {_show(b)} |" for c, a, b in self.differs]
        if self.provenance:
            lines.append("the stored row was made with other code, packages or CPU than this replay:")
            lines += [f"  {c}: stored {_show(a)}, now {_show(b)}" for c, a, b in self.provenance]
        elif not self.identical:
            lines.append("same code revision and package versions: a CPU with other vector kernels rounds "
                         "differently (docs/decisions/0024-numerics-across-cpus.md); on the machine that made the "
                         "row this is a reproducibility bug")
        return "\n".join(lines)


def _show(value: Any, width: int = 48) -> str:
    text = repr(value)
    return text if len(text) <= width else text[: width - 1] + "…"


def _same(a: Any, b: Any) -> bool:
    """Equal as stored values: both missing (None, NaN), or the same text, flag or number (numbers as doubles,
    exactly: an integer column reads back as int, a float one as float)."""
    if _missing(a) or _missing(b):
        return _missing(a) and _missing(b)
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return float(a) == float(b)
    return a == b


def _missing(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def _stored_row(sweep_dir: AnyPath, cell_id: str, domain: str, method: str) -> dict[str, Any]:
    import pyarrow.parquet as pq

    path = store.cell_path(sweep_dir, domain, method, cell_id)
    if not store.is_done(sweep_dir, domain, method, cell_id):
        raise SweepError(f"cell {cell_id} has no row in {sweep_dir} (not finished yet?): nothing to replay")
    # A local file by its path, not a Python file object: an Arrow pool thread may drop its last reference to such
    # an object just after the read, and if the interpreter is exiting by then (a quick refusal below), that
    # thread is ended inside a C++ destructor: "terminate called without an active exception", exit 134.
    if hasattr(path, "open_input"):
        with path.open_input() as fh:
            table = pq.read_table(fh)
    else:
        table = pq.read_table(str(path))
    row = table.to_pylist()[0]
    return {k: (str(v) if k in ("domain", "method") and v is not None else v) for k, v in row.items()}


def _base(spec: CellSpec, sweep_dir: AnyPath) -> BaseModel:
    """The sweep's stored base, or the same base trained again (never written to the sweep). A stored base that
    cannot be read safely (asp_dist.training.artefacts) is named in one warning line, never unpickled, and left
    where it is: a replay writes nothing to the sweep (the next sweep run sets it aside)."""
    path = base_path(store.bases_dir(sweep_dir), spec.base_key)
    try:
        return base_from_bytes(path.read_bytes(), spec, what=f"base file {path}")
    except FileNotFoundError:
        pass
    except DamagedArtefact as err:
        print(f"asp-dist: warning: {err}; the base is trained again for this replay", file=sys.stderr, flush=True)
    return train_accepted_base(spec)


def replay_cell(sweep_dir: AnyPath, cell_id: str) -> Replay:
    """Train `cell_id` of the sweep in `sweep_dir` again as it was trained, and compare the rows."""
    import torch

    from asp_dist.training.cell import run_cell
    from asp_dist.training.engines import run_pack
    from asp_dist.training.pipeline import CellDiverged
    from asp_dist.training.row import environment_columns

    manifest = store.read_manifest(sweep_dir)
    if manifest is None:
        raise SweepError(f"{sweep_dir} is not a sweep (no manifest.json)")
    check_manifest_shape(manifest, sweep_dir)
    if cell_id not in manifest["cells"]:
        raise SweepError(f"no cell {cell_id!r} in sweep {manifest['name']!r}; `asp-dist query {sweep_dir} "
                         f"--columns cell_id` lists them")
    specs = [CellSpec.from_dict(d).resolved() for d in manifest["specs"]]
    spec = specs[manifest["cells"].index(cell_id)]
    if spec.cell_id != cell_id:
        raise SweepError(f"cell {cell_id} no longer resolves to its id with this code (now {spec.cell_id}): its "
                         f"spec or a domain default changed, so it cannot be replayed as it was")
    stored = _stored_row(sweep_dir, cell_id, spec.domain, spec.method)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    if stored.get("pack"):
        units = [u for u in make_units(specs, stored_packing(manifest)) if cell_id in u.cell_ids]
        if not units or units[0].pack_id != stored["pack"]:
            raise SweepError(f"cell {cell_id} was trained in pack {stored['pack']}, which this code no longer "
                             f"builds from the manifest's grid and packing: it cannot be replayed as it was")
        members = list(units[0].specs)
        bases = {s.base_key: _base(s, sweep_dir) for s in members}
        (result,) = [r for r in run_pack(members, bases=bases) if r.spec.cell_id == cell_id]
        if result.row is None:
            raise SweepError(f"cell {cell_id} failed in its replay: {result.error}")
        replayed, how = dict(result.row, pack=stored["pack"]), f"in its pack {stored['pack']} ({len(members)} cells)"
    else:
        try:
            replayed, how = run_cell(spec, base=_base(spec, sweep_dir)), "alone"
        except (BaseRejected, CellDiverged, InvalidRow) as err:
            raise SweepError(f"cell {cell_id} failed in its replay: {err}") from None
    seconds = time.perf_counter() - t0
    skip = VOLATILE_COLUMNS | set(PROVENANCE)
    columns = [c for c in stored if c not in skip]
    differs = [(c, stored[c], replayed.get(c)) for c in columns if not _same(stored[c], replayed.get(c))]
    now = environment_columns()
    # A value the stored row lacks (a row older than its column, e.g. cpu_model) says nothing: not a difference.
    provenance = [(c, stored.get(c), now[c]) for c in ("code_revision", "asp_dist_version", "torch_version",
                                                        "numpy_version", "python_version", "cpu_model")
                  if c in now and not _missing(stored.get(c)) and not _same(stored.get(c), now[c])]
    return Replay(cell_id, how, seconds, len(columns), differs, provenance)
