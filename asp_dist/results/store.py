"""The Parquet result store of a sweep: pinned schema, one atomic file per cell, reading.

Layout of one sweep (``results/<sweep>/``)::

    manifest.json                        the grid (resolved specs) and its hash
    cells/domain=<d>/method=<m>/<cell_id>.parquet   one row per finished cell
    failed/<cell_id>.json                a cell that kept failing, with its error
    bases/<base_key>.pt                  shared base models (asp_dist.sweep.base_cache)
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

import json
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import pyarrow as pa

from asp_dist.fsutil import atomic_write, write_table_once
from asp_dist.training.row import PARTITION_COLUMNS, row_table, schema

CELLS_DIR = "cells"
FAILED_DIR = "failed"
MANIFEST = "manifest.json"
SWEEP_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")  # a directory name, never a path


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

