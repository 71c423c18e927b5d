"""THE result row: what one finished cell records, and its pinned Arrow schema.

run_cell builds the row here; the store (asp_dist.results.store) validates it against
`schema()` and writes it; every reader reads with `schema()`. A column is added in one place (a knob
of CellSpec or a domain's card, a metric of a card, or one of `_identity_columns`, `_outcome_columns`,
SWEEP_COLUMNS below), and everything downstream follows.

No torch at import (only `environment_columns` asks for its version): the store, `asp-dist status` and
`query` read and validate rows with this schema without loading torch.

Column order: the spec's fields, identity and base, the metrics of every domain (``eval_*``),
loss diagnostics, figure data, timings, environment, resumption, then the sweep's own columns.
"""

from __future__ import annotations

import json
import platform
import socket
import subprocess
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa

from asp_dist import __version__
from asp_dist.core.registry import DOMAINS
from asp_dist.errors import SchemaError
from asp_dist.machine import cpu_model
from asp_dist.spec import FIELD_NAMES, CellSpec, field_type

if TYPE_CHECKING:
    from asp_dist.core.contract import Domain
    from asp_dist.training.bases import BaseModel

PHASES = ("base", "data", "train", "eval")
LOSS_TERMS = ("self_play", "paired", "unpaired", "disc", "total")
# Columns that legitimately differ between two runs of the same spec (time, place, resumption).
VOLATILE_COLUMNS = frozenset(
    [f"time_{p}_{k}" for p in PHASES + ("total",) for k in ("wall_s", "cpu_s")]
    + ["base_train_wall_s", "base_train_cpu_s", "node", "cpu_model", "finished_at", "resumed_from_step", "base_reused"]
)
# Stored dictionary-encoded, so that hive-style directories of the same names agree with them.
PARTITION_COLUMNS = ("domain", "method")
# Columns the sweep service adds to run_cell's row. `pack`: the pack a cell was trained in
# (asp_dist.sweep.packing, e.g. "particles/trial-3/4f1c2a/1of1-k21"), null for a cell trained alone;
# rows written before packs existed lack the column and read as null.
SWEEP_COLUMNS: tuple[tuple[str, pa.DataType], ...] = (
    ("sweep_id", pa.string()), ("ray_node_id", pa.string()), ("ray_version", pa.string()), ("pack", pa.string()),
)
_ARROW_TYPES = {bool: pa.bool_(), int: pa.int64(), float: pa.float64(), str: pa.string()}


def _identity_columns() -> list[tuple[str, pa.DataType]]:
    return [
        ("cell_id", pa.string()), ("seed_init", pa.int64()), ("seed_train", pa.int64()),
        ("base_key", pa.string()), ("base_score", pa.float64()), ("base_attempts", pa.int64()),
        ("base_seed", pa.int64()), ("base_attempt_scores", pa.string()), ("base_reused", pa.bool_()),
        ("base_train_wall_s", pa.float64()), ("base_train_cpu_s", pa.float64()),
    ]


def _outcome_columns() -> list[tuple[str, pa.DataType]]:
    cols: list[tuple[str, pa.DataType]] = [("eval_mixed_higher_is_better", pa.bool_()),
                                           ("metric_directions", pa.string())]
    cols += [(f"loss_{k}", pa.float64()) for k in LOSS_TERMS]
    cols.append(("figure_data", pa.string()))
    cols += [(f"time_{p}_{k}", pa.float64()) for p in PHASES + ("total",) for k in ("wall_s", "cpu_s")]
    cols += [(name, pa.string()) for name in ("node", "cpu_model", "finished_at", "asp_dist_version", "torch_version",
                                               "numpy_version", "python_version", "code_revision")]
    cols.append(("resumed_from_step", pa.int64()))
    return cols


def _included(domain: str | None) -> list[Any]:
    """The domains whose knobs and metrics a row has: every registered one (domain None: what readers read
    with), or the legacy four (Domain.legacy_identity: every row had their columns before domains were
    plugins) and the row's own. So installing a plugin changes the shape of no built-in domain's row."""
    if domain is None or domain not in DOMAINS:
        return list(DOMAINS.values())
    return [d for d in DOMAINS.values() if d.legacy_identity or d.name == domain]


def metric_names(domain: str | None = None) -> list[str]:
    """The metrics of the domains a row has (an ``eval_<name>`` column each): see _included."""
    return sorted({m for d in _included(domain) for m in d.metrics})


@lru_cache(maxsize=None)
def schema(domain: str | None = None) -> pa.Schema:
    """The pinned schema of a result row of `domain` (None: the union over every registered domain)."""
    included = _included(domain)
    knobs = {k.name for d in included for k in d.knobs}
    other = {k.name for d in DOMAINS.values() for k in d.knobs} - knobs
    fields: list[pa.Field] = []
    for name in FIELD_NAMES:
        if name in other:
            continue
        t = pa.dictionary(pa.int32(), pa.string()) if name in PARTITION_COLUMNS else _ARROW_TYPES[field_type(name)]
        fields.append(pa.field(name, t))
    fields += [pa.field(n, t) for n, t in _identity_columns()]
    fields += [pa.field(f"eval_{m}", pa.float64()) for m in metric_names(domain)]
    fields += [pa.field(n, t) for n, t in _outcome_columns()]
    fields += [pa.field(n, t) for n, t in SWEEP_COLUMNS]
    names = [f.name for f in fields]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # a plugin's knob or metric named like a column of the row (e.g. a domain "base" with base_key)
        raise SchemaError(f"the row schema has column(s) {', '.join(twice)} twice: a domain's knob or metric "
                          f"(domains {', '.join(d.name for d in included)}) is named like a column of the row")
    return pa.schema(fields)


CURVE_KEYS = ("cell_id", "domain", "method", "paired", "trial")
CURVE_DIAGNOSTICS = ("lambda_unpaired_now", *(f"loss_{k}" for k in LOSS_TERMS), "disc_acc_real", "disc_acc_fake",
                     "d_fake")


@lru_cache(maxsize=None)
def curve_schema(domain: str | None = None) -> pa.Schema:
    """The pinned schema of a learning curve: one row per point of one cell (asp_dist.training.trainer)."""
    fields = [pa.field(n, pa.dictionary(pa.int32(), pa.string()) if n in PARTITION_COLUMNS else
                       (pa.int64() if n in ("paired", "trial") else pa.string())) for n in CURVE_KEYS]
    fields.append(pa.field("step", pa.int64()))
    fields += [pa.field(n, pa.float64()) for n in CURVE_DIAGNOSTICS]
    fields += [pa.field(f"probe_{m}", pa.float64()) for m in metric_names(domain)]
    return pa.schema(fields)


def curve_table(row: dict[str, Any], curve: list[dict[str, float]]) -> pa.Table:
    """A cell's curve points as a table with the pinned curve schema (keys repeated from its row)."""
    sch = curve_schema(row.get("domain"))
    unknown = sorted({k for point in curve for k in point} - set(sch.names))
    if unknown:
        raise SchemaError(f"curve has column(s) not in the pinned schema: {', '.join(unknown)}; "
                          f"add them to asp_dist/training/row.py")
    arrays = []
    for f in sch:
        if f.name in CURVE_KEYS:
            values = [row[f.name]] * len(curve)
        else:
            values = [point.get(f.name) for point in curve]
            values = [int(v) for v in values] if f.name == "step" else values
        if pa.types.is_dictionary(f.type):
            arrays.append(pa.array(values, pa.string()).dictionary_encode())
        else:
            arrays.append(pa.array(values, f.type))
    return pa.Table.from_arrays(arrays, schema=sch)


def row_table(row: dict[str, Any]) -> pa.Table:
    """One row as a table with its domain's pinned schema; missing columns are null, unknown ones an error
    (another domain's knob is dropped while unset: CellSpec.to_dict lists every registered domain's)."""
    sch = schema(row.get("domain"))
    every = set(schema().names)
    unknown = sorted(k for k, v in row.items() if k not in sch.names and (k not in every or v is not None))
    if unknown:
        raise SchemaError(f"row has column(s) not in the pinned schema: {', '.join(unknown)}; "
                          f"add them to asp_dist/training/row.py")
    arrays = []
    for f in sch:
        value = row.get(f.name)
        if pa.types.is_dictionary(f.type):
            arrays.append(pa.array([value], pa.string()).dictionary_encode())
        else:
            arrays.append(pa.array([value], f.type))
    return pa.Table.from_arrays(arrays, schema=sch)


class InvalidRow(RuntimeError):
    """A cell whose evaluation gave no valid row (a declared metric missing or not finite): the cell fails,
    is recorded under failed/ with this one line, and `resume` tries it again; no row is written."""


def build_row(spec: CellSpec, domain: "Domain", base: "BaseModel", *, base_reused: bool, metrics: dict[str, float],
              losses: dict[str, float | None], figure: dict | None, timings: dict[str, float],
              resumed_from: int | None) -> dict[str, Any]:
    """The flat row of one finished cell (scalars and strings only); InvalidRow unless every metric the domain
    declares is there and finite: a row is the record that a cell is done, so it must be one stats can use."""
    from asp_dist.core.contract import metric_problem

    problem = metric_problem(domain, metrics)
    if problem is not None:
        # No cell id in the message: `status` groups failures by their text, and the record names its cell.
        raise InvalidRow(f"{spec.domain} evaluate gave no valid row: {problem}; no row written")
    row: dict[str, Any] = spec.to_dict()
    row.update({"cell_id": spec.cell_id, "seed_init": spec.seed_for("init"), "seed_train": spec.seed_for("train")})
    meta = base.meta()
    row.update({k: v for k, v in meta.items() if k != "base_attempt_scores"})
    row["base_attempt_scores"] = json.dumps(meta["base_attempt_scores"])
    row.update({"base_reused": base_reused, "base_train_wall_s": base.train_wall_s, "base_train_cpu_s": base.train_cpu_s})
    row.update({f"eval_{k}": float(v) for k, v in metrics.items()})
    row["eval_mixed_higher_is_better"] = domain.metrics["mixed"].higher_is_better
    row["metric_directions"] = json.dumps({k: ("higher" if m.higher_is_better else "lower")
                                           for k, m in domain.metrics.items()}, sort_keys=True)
    row.update(losses)
    row["figure_data"] = json.dumps(figure) if figure is not None else None
    row.update(timings)
    row.update(environment_columns())
    row["resumed_from_step"] = resumed_from
    return row


def comparable(row: dict[str, Any]) -> dict[str, Any]:
    """A row without the columns that differ between runs of one spec (for equality checks)."""
    return {k: v for k, v in row.items() if k not in VOLATILE_COLUMNS}


def environment_columns() -> dict[str, Any]:
    import torch  # here, not at the top: the schema above is read by commands that never train

    return {
        "node": socket.gethostname(),
        # The CPU and the vector kernels torch picked on it: floats reproduce bit for bit only on the same kind
        # (docs/decisions/0024-numerics-across-cpus.md, 0041-every-row-names-its-cpu.md). Rows written before
        # this column read it as null.
        "cpu_model": f"{cpu_model()} ({torch.backends.cpu.get_cpu_capability()})",
        "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "asp_dist_version": __version__,
        "torch_version": torch.__version__,
        "numpy_version": np.__version__,
        "python_version": platform.python_version(),
        "code_revision": code_revision(),
    }


@lru_cache(maxsize=1)
def code_revision() -> str:
    """Git commit of the asp_dist source (with '+dirty' for local changes), or 'unknown'."""
    root = Path(__file__).resolve().parents[2]
    try:
        sha = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=root, capture_output=True,
                             text=True, timeout=5).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "asp_dist"], cwd=root,
                               capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (sha + ("+dirty" if dirty else "")) if sha else "unknown"


