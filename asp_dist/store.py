"""The Parquet result store of a sweep: pinned schema, one atomic file per cell, reading.

Layout of one sweep (``results/<sweep>/``)::

    manifest.json                        the grid (resolved specs) and its hash
    cells/domain=<d>/method=<m>/<cell_id>.parquet   one row per finished cell
    failed/<cell_id>.json                a cell that kept failing, with its error
    bases/<base_key>.pt                  shared base models (asp_dist.base_cache)
    tune/                                Ray Tune's experiment state and checkpoints

The Parquet file of a cell is the record that the cell is done: it is written once, under a
fixed name, through a hidden temp file and an atomic link/rename, and never overwritten.

``domain`` and ``method`` are stored dictionary-encoded inside each file. That is what lets
the hive-style directories and the same-named columns agree: pandas.read_parquet(dir),
pyarrow.dataset.dataset(dir) and DuckDB read_parquet('dir/**/*.parquet') all read the
directory as-is (plain string columns would make pandas fail with "Unable to merge").
No Ray import here: the stats job and tests read results without starting Ray.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import tempfile
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from asp_dist.spec import FIELD_NAMES, field_type

CELLS_DIR = "cells"
FAILED_DIR = "failed"
MANIFEST = "manifest.json"
PARTITION_COLUMNS = ("domain", "method")
SWEEP_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")  # a directory name, never a path
_ARROW_TYPES = {bool: pa.bool_(), int: pa.int64(), float: pa.float64(), str: pa.string()}


class SchemaError(ValueError):
    """A row whose columns do not match the pinned schema (a schema drift: update store.py)."""


# ---- the pinned schema ------------------------------------------------------------------------
def _cell_columns() -> list[tuple[str, pa.DataType]]:
    """Every non-spec, non-metric column that asp_dist.cell.run_cell writes, with its type."""
    from asp_dist.cell import PHASES

    cols: list[tuple[str, pa.DataType]] = [
        ("cell_id", pa.string()), ("seed_init", pa.int64()), ("seed_train", pa.int64()),
        ("base_key", pa.string()), ("base_score", pa.float64()), ("base_attempts", pa.int64()),
        ("base_seed", pa.int64()), ("base_attempt_scores", pa.string()), ("base_reused", pa.bool_()),
        ("base_train_wall_s", pa.float64()), ("base_train_cpu_s", pa.float64()),
        ("eval_mixed_higher_is_better", pa.bool_()), ("metric_directions", pa.string()),
    ]
    cols += [(f"loss_{k}", pa.float64()) for k in ("self_play", "paired", "unpaired", "disc", "total")]
    cols.append(("figure_data", pa.string()))
    cols += [(f"time_{p}_{k}", pa.float64()) for p in PHASES + ("total",) for k in ("wall_s", "cpu_s")]
    cols += [(name, pa.string()) for name in ("node", "finished_at", "asp_dist_version", "torch_version",
                                               "numpy_version", "python_version", "code_revision")]
    cols.append(("resumed_from_step", pa.int64()))
    return cols


# Columns the sweep service adds to run_cell's row.
SWEEP_COLUMNS: tuple[tuple[str, pa.DataType], ...] = (
    ("sweep_id", pa.string()), ("ray_node_id", pa.string()), ("ray_version", pa.string()),
)


def metric_names() -> list[str]:
    """Union of the metrics of every domain whose module is present (absent ones add nothing yet)."""
    from asp_dist.domains import DOMAINS, available_domains

    names: list[str] = []
    for domain in available_domains():
        module_name, cls_name = DOMAINS[domain].split(":")
        cls = getattr(importlib.import_module(module_name), cls_name)
        names += [m for m in cls.metrics if m not in names]
    return sorted(names)


@lru_cache(maxsize=1)
def schema() -> pa.Schema:
    """The pinned schema of a result row: spec, identity/base, metrics, losses, timings, env, sweep."""
    fields: list[pa.Field] = []
    for name in FIELD_NAMES:
        t = pa.dictionary(pa.int32(), pa.string()) if name in PARTITION_COLUMNS else _ARROW_TYPES[field_type(name)]
        fields.append(pa.field(name, t))
    cell_cols = _cell_columns()
    fields += [pa.field(n, t) for n, t in cell_cols[:11]]  # identity and base columns first
    fields += [pa.field(f"eval_{m}", pa.float64()) for m in metric_names()]
    fields += [pa.field(n, t) for n, t in cell_cols[11:]]
    fields += [pa.field(n, t) for n, t in SWEEP_COLUMNS]
    return pa.schema(fields)


def row_table(row: dict[str, Any]) -> pa.Table:
    """One row as a table with the pinned schema; missing columns are null, unknown ones an error."""
    sch = schema()
    unknown = sorted(set(row) - set(sch.names))
    if unknown:
        raise SchemaError(f"row has column(s) not in the pinned schema: {', '.join(unknown)}; "
                          f"add them to asp_dist/store.py")
    arrays = []
    for f in sch:
        value = row.get(f.name)
        if pa.types.is_dictionary(f.type):
            arrays.append(pa.array([value], pa.string()).dictionary_encode())
        else:
            arrays.append(pa.array([value], f.type))
    return pa.Table.from_arrays(arrays, schema=sch)


# ---- paths -----------------------------------------------------------------------------------
def cells_dir(sweep_dir: Path) -> Path:
    return Path(sweep_dir) / CELLS_DIR


def cell_path(sweep_dir: Path, domain: str, method: str, cell_id: str) -> Path:
    return cells_dir(sweep_dir) / f"domain={domain}" / f"method={method}" / f"{cell_id}.parquet"


def is_done(sweep_dir: Path, domain: str, method: str, cell_id: str) -> bool:
    return cell_path(sweep_dir, domain, method, cell_id).exists()


def done_cell_ids(sweep_dir: Path) -> set[str]:
    """Cells with a finished Parquet file (hidden temp files are ignored)."""
    root = cells_dir(sweep_dir)
    if not root.exists():
        return set()
    return {p.stem for p in root.glob("domain=*/method=*/*.parquet") if not p.name.startswith((".", "_"))}


# ---- writing -----------------------------------------------------------------------------------
def write_row(sweep_dir: Path, row: dict[str, Any], sweep_id: str) -> bool:
    """Write one finished cell. Returns False (and writes nothing) if the cell already has a file."""
    row = dict(row, sweep_id=sweep_id)
    table = row_table(row)  # validate before touching the disk
    final = cell_path(sweep_dir, row["domain"], row["method"], row["cell_id"])
    return write_table_once(table, final)


def write_table_once(table: pa.Table, final: Path) -> bool:
    """Write `table` to `final` through a hidden temp file and an atomic link; never overwrites.
    Returns False (and writes nothing) if `final` already exists."""
    final = Path(final)
    if final.exists():
        return False
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=".tmp", dir=final.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        try:
            os.link(tmp, final)  # atomic and never overwrites: a racing writer loses cleanly
        except FileExistsError:
            return False
        except OSError:
            # Filesystems without hard links: rename is still atomic (last writer wins; rows are equal).
            os.replace(tmp, final)
            return True
        return True
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write(path: Path, data: bytes | str) -> None:
    """Replace `path` with `data` through a hidden temp file, fsync and rename: readers see the
    old file or the new one, never half of it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data.encode() if isinstance(data, str) else data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def record_failure(sweep_dir: Path, cell_id: str, domain: str, method: str, error: str) -> None:
    """Record a cell that kept failing; it stays out of the dataset and is retried on resume."""
    path = Path(sweep_dir) / FAILED_DIR / f"{cell_id}.json"
    previous = json.loads(path.read_text()) if path.exists() else {}
    info = {"cell_id": cell_id, "domain": domain, "method": method, "error": error[-4000:],
            "failed_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "times_failed": int(previous.get("times_failed", 0)) + 1}
    atomic_write(path, json.dumps(info, indent=1))


def clear_failure(sweep_dir: Path, cell_id: str) -> None:
    path = Path(sweep_dir) / FAILED_DIR / f"{cell_id}.json"
    if path.exists():
        path.unlink()


def failed_cells(sweep_dir: Path) -> dict[str, dict[str, Any]]:
    root = Path(sweep_dir) / FAILED_DIR
    if not root.exists():
        return {}
    return {p.stem: json.loads(p.read_text()) for p in sorted(root.glob("*.json")) if not p.name.startswith(".")}


# ---- manifest ----------------------------------------------------------------------------------
def write_manifest(sweep_dir: Path, manifest: dict[str, Any]) -> None:
    atomic_write(Path(sweep_dir) / MANIFEST, json.dumps(manifest, indent=1, sort_keys=True))


def read_manifest(sweep_dir: Path) -> dict[str, Any] | None:
    path = Path(sweep_dir) / MANIFEST
    return json.loads(path.read_text()) if path.exists() else None


# ---- reading -----------------------------------------------------------------------------------
def read_table(sweep_dir: Path) -> pa.Table:
    """All finished rows of a sweep as one Arrow table with the pinned schema."""
    import pyarrow.dataset as ds

    root = cells_dir(sweep_dir)
    files = sorted(str(p) for p in root.glob("domain=*/method=*/*.parquet") if not p.name.startswith((".", "_"))) \
        if root.exists() else []
    if not files:
        return schema().empty_table()
    # Explicit schema: files written before a domain was added lack its metric columns -> null.
    return ds.dataset(files, schema=schema(), format="parquet").to_table()


def read_rows(sweep_dir: Path) -> "pandas.DataFrame":  # noqa: F821
    """All finished rows of a sweep as a DataFrame (domain and method as plain strings)."""
    df = read_table(sweep_dir).to_pandas()
    for col in PARTITION_COLUMNS:
        df[col] = df[col].astype(str) if len(df) else df[col].astype(object)
    return df.sort_values("cell_id", kind="stable").reset_index(drop=True)

