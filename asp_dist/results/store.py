"""The result store of a sweep: its directory layout, writing, failures, manifest, and THE reader.

Layout of one sweep (``<results>/<sweep>/``)::

    manifest.json                        the grid (resolved specs) and its hash
    cells/domain=<d>/method=<m>/<cell_id>.parquet   one row per finished cell
    curves/domain=<d>/method=<m>/<cell_id>.parquet  its learning curve (~50 rows), written just before it
    failed/<cell_id>.json                a cell that kept failing, with its error
    bases/<base_key>.pt                  shared base models (asp_dist.sweep.base_cache)
    tune/                                Ray Tune's experiment state and checkpoints

The Parquet file of a cell is the record that the cell is done: it is written once, under a
fixed name, through a hidden temp file and an atomic link/rename, and never overwritten. Names
that start with ``.`` or ``_`` are temp files of an unfinished write and are never read.

``domain`` and ``method`` are stored dictionary-encoded inside each file. That is what lets
the hive-style directories and the same-named columns agree: pandas.read_parquet(dir),
pyarrow.dataset.dataset(dir) and DuckDB read_parquet('dir/**/*.parquet') all read the
directory as-is (plain string columns would make pandas fail with "Unable to merge").

THE reader (cell_files, read_table, read_rows) verifies every cell file against this layout before it
counts: one row, its cell_id the file's name, its domain and method its directories', no cell twice.
A stray, planted or truncated file is named in a warning and left out (or, with ``strict=True``,
refused with SchemaError).

Everything that knows this layout is here; the sweep ledger, ``asp-dist query`` and the stats
job ask this module. No Ray import: results are read without starting Ray.

A sweep lives in a local directory (a ``Path``: every local code path is unchanged) or under an
S3 prefix (``s3://bucket/prefix/<sweep>``, an ``asp_dist.results.s3.S3Path`` with the same
pathlib API). On S3 a cell's file is one conditional PUT (``If-None-Match: *``): created once,
atomically, never overwritten; a failure record or the manifest is one whole-object PUT.

(About 515 lines, over the project's 500: the layout, its writers and THE reader are kept in one module on
purpose, so that whatever knows where a file goes also knows what makes it count.)
"""

from __future__ import annotations

import json
import os
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pyarrow as pa

from asp_dist.errors import SchemaError
from asp_dist.results.location import (
    AnyPath,
    as_path,
    move_aside,
    parquet_dataset,
    parquet_file,
    parquet_metadata,
    write_replace,
    write_table_once,
)
from asp_dist.results.s3 import S3Path, check_bucket
from asp_dist.training.row import PARTITION_COLUMNS, curve_schema, curve_table, row_table, schema

if TYPE_CHECKING:
    import pandas as pd

CELLS_DIR = "cells"
CURVES_DIR = "curves"
FAILED_DIR = "failed"
BASES_DIR = "bases"
MANIFEST = "manifest.json"
DEFAULT_RESULTS = "results"


# ---- layout ------------------------------------------------------------------------------------
def cells_dir(sweep_dir: str | AnyPath) -> AnyPath:
    return as_path(sweep_dir) / CELLS_DIR


def bases_dir(sweep_dir: str | AnyPath) -> AnyPath:
    return as_path(sweep_dir) / BASES_DIR


def base_path(cache_dir: str | AnyPath, base_key: str) -> AnyPath:
    """Where a base cache (bases_dir; asp_dist.sweep.base_cache) keeps the base `base_key`."""
    return as_path(cache_dir) / f"{base_key}.pt"


def rejected_base_path(cache_dir: str | AnyPath, base_key: str) -> AnyPath:
    """Where it remembers that no attempt could train that base to its bar."""
    return as_path(cache_dir) / f"{base_key}.rejected.json"


def cell_path(sweep_dir: str | AnyPath, domain: str, method: str, cell_id: str) -> AnyPath:
    return cells_dir(sweep_dir) / f"domain={domain}" / f"method={method}" / f"{cell_id}.parquet"


def curve_path(sweep_dir: str | AnyPath, domain: str, method: str, cell_id: str) -> AnyPath:
    return as_path(sweep_dir) / CURVES_DIR / f"domain={domain}" / f"method={method}" / f"{cell_id}.parquet"


def is_sweep_dir(path: str | AnyPath) -> bool:
    """A directory the sweep service wrote (it has a manifest or a cells/ folder)."""
    path = as_path(path)
    return (path / MANIFEST).is_file() or (path / CELLS_DIR).is_dir()


def locate_sweep(name_or_path: str | AnyPath, results: str | AnyPath = DEFAULT_RESULTS) -> AnyPath:
    """A path as given, or ``<results>/<name>`` for a bare sweep name (as `asp-dist status NAME` takes).
    An ``s3://`` path is taken as given, and with ``--results s3://bucket/prefix`` a bare name that is
    not a local path is the sweep under that prefix; the bucket is checked first (one clear line for an
    endpoint that does not answer, refused credentials or a missing bucket)."""
    if isinstance(name_or_path, S3Path) or str(name_or_path).startswith("s3://"):
        path = as_path(str(name_or_path))
        check_bucket(path)
        return path
    if isinstance(results, S3Path) or str(results).startswith("s3://"):
        path = Path(name_or_path).expanduser()
        if path.exists() or len(path.parts) != 1:
            return path
        root = as_path(str(results))
        check_bucket(root)
        return root / path.name
    path = Path(name_or_path).expanduser()
    candidate = Path(results).expanduser() / path
    if not path.exists() and len(path.parts) == 1 and candidate.is_dir():
        return candidate
    return path


def visible(path: AnyPath, root: AnyPath) -> bool:
    """False for a file inside a hidden or temp name below `root` (an unfinished write)."""
    return not any(p.startswith((".", "_")) for p in path.relative_to(root).parts)


def cell_files(sweep_dir: str | AnyPath, strict: bool = False, remember: bool = False) -> list[AnyPath]:
    """The finished cells' Parquet files of a sweep, sorted; temp files of unfinished writes are left out.

    Each file is verified to be what the store writes (cell_file_problem): one row, whose cell_id is the
    file's name and whose domain and method are its directories', and no cell twice. A file that is not
    (stray, planted, truncated, copied) is never counted: it is named in a warning on stderr, or, with
    `strict`, refused with a SchemaError. `remember`: keep the verdicts in the sweep's verdict index (the
    sweep's driver does, under the sweep's lock; readers only read the index, so they never write)."""
    root = cells_dir(sweep_dir)
    if not isinstance(root, S3Path) and not root.is_dir():  # on S3 the listing below answers that too
        return []
    good: list[AnyPath] = []
    seen: dict[str, AnyPath] = {}
    paths = sorted(p for p in root.rglob("*.parquet") if visible(p, root) and p.is_file())
    for path, problem in zip(paths, _problems(paths, root, remember)):
        if problem is None and path.stem in seen:
            problem = f"repeats cell {path.stem}, already in {seen[path.stem]}"
        if problem is not None:
            _reject(path, problem, strict)
            continue
        seen[path.stem] = path
        good.append(path)
    return good


_CHECKED: dict[str, tuple[tuple[int, int, int], str | None]] = {}  # path -> (inode, size, mtime), verdict
VERIFY_THREADS = 4  # at most; footers are parsed (and on S3 fetched) in parallel: pyarrow releases the GIL meanwhile

# The verdicts the sweep's driver reached, kept on disk so that the next process (`asp-dist status`, `query`,
# a resumed driver) does not parse 1,470 footers again. A cache, never the truth: an entry counts only while the file keeps the
# inode, size and mtime it had when it was found good (a truncated, rewritten or copied file is verified
# again), and a missing, stale or unreadable index only costs the time it saves. Local disk only (on S3 the
# listing already gives size and Last-Modified, and status is dominated by the requests).
VERDICTS_FILE = ".verified.json"  # in cells/: a hidden name, so no reader of the dataset ever sees it
_VERDICTS_VERSION = 2  # 2: a good verdict also says the required metrics (contract.REQUIRED_METRICS) are finite
_INDEXED: dict[str, dict[str, list[int]]] = {}  # cells/ root -> the good verdicts its index holds (as read or written)


def _load_verdicts(root: AnyPath) -> None:
    """Read root's verdict index into _CHECKED once per process (verdicts already reached here win)."""
    if isinstance(root, S3Path) or str(root) in _INDEXED:
        return
    _INDEXED[str(root)] = {}
    try:
        index = json.loads((root / VERDICTS_FILE).read_text())
        good = index["good"] if index.get("version") == _VERDICTS_VERSION else {}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return
    for rel, key in good.items() if isinstance(good, dict) else ():
        if isinstance(key, list) and len(key) == 3 and all(isinstance(k, int) for k in key):
            _CHECKED.setdefault(str(root / rel), (tuple(key), None))
            _INDEXED[str(root)][rel] = key


def _save_verdicts(root: AnyPath, paths: list[AnyPath]) -> None:
    """Write the good verdicts of `paths` as root's index, if it does not hold exactly those (tmp file +
    rename: a reader sees the old or the new index whole). Best effort: a read-only or full disk leaves the
    index as it was."""
    if isinstance(root, S3Path):
        return
    good = {}
    for path in paths:
        cached = _CHECKED.get(str(path))
        if cached is not None and cached[1] is None:
            good[path.relative_to(root).as_posix()] = list(cached[0])
    if _INDEXED.get(str(root)) == good:
        return
    tmp = root / f".verified.{os.getpid()}.tmp"
    try:
        tmp.write_text(json.dumps({"version": _VERDICTS_VERSION, "good": good}, separators=(",", ":")))
        os.replace(tmp, root / VERDICTS_FILE)
        _INDEXED[str(root)] = good
    except OSError:
        tmp.unlink(missing_ok=True)


def _problems(paths: list[AnyPath], root: AnyPath, remember: bool = False) -> list[str | None]:
    """cell_file_problem of each path, in order; a large sweep's files in a few threads (status of a
    1,470-cell sweep is mostly this, unless the verdict index already knows the files). `remember`: bring
    the index up to date."""
    _load_verdicts(root)
    threads = VERIFY_THREADS if isinstance(root, S3Path) else min(VERIFY_THREADS, os.cpu_count() or 1)
    if len(paths) < 64 or threads == 1:
        problems = [cell_file_problem(p, root) for p in paths]
    else:
        from concurrent.futures import ThreadPoolExecutor

        # One task per thread, not per file: a future per file costs as much as parsing its footer.
        share = -(-len(paths) // threads)
        parts = [paths[k:k + share] for k in range(0, len(paths), share)]
        with ThreadPoolExecutor(len(parts)) as pool:
            problems = [q for part in pool.map(lambda part: [cell_file_problem(p, root) for p in part], parts)
                        for q in part]
    if remember:
        _save_verdicts(root, paths)
    return problems


_WARNED: set[tuple[str, str]] = set()


def cell_file_problem(path: AnyPath, root: AnyPath) -> str | None:
    """None for a cell file as write_row leaves it under `root` (a sweep's cells/), else what is wrong.
    Finished files never change, so a verdict is kept while the file's inode, size and mtime stay the same
    (on S3: its size and Last-Modified, known from the listing)."""
    try:
        st = path.stat()
    except OSError as err:
        return f"cannot be read ({err.strerror or err})"
    key = (st.st_ino, st.st_size, st.st_mtime_ns)
    cached = _CHECKED.get(str(path))
    if cached is not None and cached[0] == key:
        return cached[1]
    parts = path.relative_to(root).parts
    if len(parts) != 3 or not parts[0].startswith("domain=") or not parts[1].startswith("method="):
        problem: str | None = f"is not in a {CELLS_DIR}/domain=<domain>/method=<method>/ directory"
    else:
        domain, method = parts[0][len("domain="):], parts[1][len("method="):]
        try:
            meta = parquet_metadata(path)
            columns = {name: _column_index(meta, name) for name in ("cell_id", *PARTITION_COLUMNS)}
            missing = [name for name, i in columns.items() if i is None]
            if missing:
                problem = f"lacks the column(s) {', '.join(missing)}; it is not a cell's row"
            elif meta.num_rows != 1:
                problem = f"holds {meta.num_rows} rows; a cell's file holds exactly one"
            else:
                row = _footer_values(path, meta, columns)
                if row["cell_id"] != path.stem:
                    problem = f"holds cell {row['cell_id']!r}, not {path.stem!r} as its name says"
                elif (row["domain"], row["method"]) != (domain, method):
                    problem = f"holds a {row['domain']}/{row['method']} row in the directory of {domain}/{method}"
                else:
                    problem = _metrics_problem(path, meta)
        except (pa.ArrowException, OSError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            problem = f"cannot be read as Parquet ({first})"
    _CHECKED[str(path)] = (key, problem)
    return problem


def _metrics_problem(path: AnyPath, meta) -> str | None:
    """What makes a cell's row unfinished: a metric every domain returns (contract.REQUIRED_METRICS) missing or
    not finite, as in a row of older code or a planted one (today's rows are checked before they are written,
    against every metric their domain declares: asp_dist.training.row.build_row)."""
    import math

    from asp_dist.core.contract import REQUIRED_METRICS

    columns = {f"eval_{m}": _column_index(meta, f"eval_{m}") for m in REQUIRED_METRICS}
    missing = [name for name, i in columns.items() if i is None]
    if missing:
        return f"lacks the metric column(s) {', '.join(missing)}; it is not a finished row"
    values = _footer_values(path, meta, columns)
    bad = [f"{name} = {values[name]}" for name in columns
           if not isinstance(values[name], (int, float)) or not math.isfinite(values[name])]
    return f"has {', '.join(bad)}; it is not a finished row" if bad else None


_COLUMN_AT: dict[str, int] = {}  # where a column was last found: the files of a sweep share their layout


def _column_index(meta, name: str) -> int | None:
    """The position of column `name` in a Parquet footer (`meta`), None where it has none. The position
    found last is tried first (one lookup instead of listing 100-odd column names per file)."""
    i = _COLUMN_AT.get(name)
    if i is not None and i < meta.num_columns and meta.schema.column(i).path == name:
        return i
    names = meta.schema.names
    if name not in names:
        return None
    _COLUMN_AT[name] = i = names.index(name)
    return i


def _footer_values(path: AnyPath, meta, columns: dict[str, int]) -> dict[str, Any]:
    """The one row's values of `columns` (name -> position) of a one-row Parquet file, from its footer
    (`meta`): a column chunk's statistics of one value have min == max == the value (pyarrow writes them),
    so no data page is read, a third of the cost of reading the columns (status of a 1,800-cell sweep
    without its verdict index). A file without such statistics has the columns read."""
    out: dict[str, Any] = {}
    group = meta.row_group(0)
    for name, i in columns.items():
        stats = group.column(i).statistics
        if stats is None or not stats.has_min_max or stats.num_values != 1 or stats.min != stats.max:
            with parquet_file(path) as whole:
                return whole.read(columns=list(columns)).to_pylist()[0]
        out[name] = stats.min
    return out


def _reject(path: AnyPath, problem: str, strict: bool) -> None:
    if strict:
        raise SchemaError(f"{path} {problem}")
    if (str(path), problem) not in _WARNED:  # once per file and process: a sweep's driver asks often
        _WARNED.add((str(path), problem))
        print(f"asp-dist: warning: {path} is not counted: it {problem}", file=sys.stderr)


def curve_files(sweep_dir: str | AnyPath) -> list[AnyPath]:
    """The learning curves' Parquet files of a sweep, sorted (one per cell that recorded one)."""
    root = as_path(sweep_dir) / CURVES_DIR
    if not isinstance(root, S3Path) and not root.is_dir():
        return []
    return sorted(p for p in root.rglob("*.parquet") if visible(p, root) and p.is_file())


def done_cell_ids(sweep_dir: str | AnyPath, strict: bool = False, remember: bool = False) -> set[str]:
    """Cells with a finished, verified Parquet file (the file name is the cell id); `remember`: cell_files."""
    return {p.stem for p in cell_files(sweep_dir, strict, remember)}


def is_done(sweep_dir: str | AnyPath, domain: str, method: str, cell_id: str) -> bool:
    """The cell has its file, and the file is a cell's row as write_row leaves it (a damaged one is not done:
    set_aside_damaged moves it away before the cell trains again)."""
    path = cell_path(sweep_dir, domain, method, cell_id)
    return path.exists() and cell_file_problem(path, cells_dir(sweep_dir)) is None


# ---- damaged cell files ----------------------------------------------------------------------------
DAMAGED_DIR = "damaged"  # <sweep>/damaged/<UTC time>/cells/...: files the reader rejected, kept for inspection


def damaged_cells(sweep_dir: str | AnyPath, grid: dict[str, tuple[str, str]]) -> dict[str, tuple[AnyPath, str]]:
    """Cells of `grid` (cell id -> (domain, method)) whose file exists under the cell's own name but is not a
    cell's row: truncated, empty, holding another cell, or a symbolic link to nothing. cell id -> (path,
    what is wrong). One listing of cells/ (on S3: no request per cell)."""
    root = cells_dir(sweep_dir)
    if not isinstance(root, S3Path) and not root.is_dir():
        return {}
    found: dict[str, tuple[AnyPath, str]] = {}
    for path in root.rglob("*.parquet"):
        cell = grid.get(path.stem)
        if cell is None or not visible(path, root) or path != cell_path(sweep_dir, *cell, path.stem):
            continue  # not a grid cell's own file: the reader warns about strays and never counts them
        if not isinstance(path, S3Path) and path.is_symlink() and not path.exists():
            found[path.stem] = (path, "is a symbolic link to nothing")
            continue
        problem = cell_file_problem(path, root)
        if problem is not None:
            found[path.stem] = (path, problem)
    return found


def damaged_stamp() -> str:
    """The UTC time that names one setting-aside: damaged/<stamp>/ keeps each file at its place in the sweep."""
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")


def damaged_dest(sweep_dir: AnyPath, stamp: str, path: AnyPath) -> AnyPath:
    """Where a damaged file of the sweep (a cell's row or curve, a base) is kept: damaged/<stamp>/<its path>."""
    return sweep_dir / DAMAGED_DIR / stamp / path.relative_to(sweep_dir)


def set_aside_damaged(sweep_dir: str | AnyPath, grid: dict[str, tuple[str, str]]) -> list[tuple[AnyPath, AnyPath, str]]:
    """Move every damaged cell file of `grid` (damaged_cells) and its curve into ``damaged/<UTC time>/``, so
    that the cell trains again and its new row is written once; returns (file, where it went, what was
    wrong). Run by the sweep's driver under the sweep's lock, before it counts what is done."""
    damaged = damaged_cells(sweep_dir, grid)
    if not damaged:
        return []
    sweep_dir = as_path(sweep_dir)
    stamp = damaged_stamp()
    moved = []
    for cell_id, (path, problem) in sorted(damaged.items()):
        domain, method = grid[cell_id]
        for old in (path, curve_path(sweep_dir, domain, method, cell_id)):
            if old is not path and not old.exists():
                continue
            new = damaged_dest(sweep_dir, stamp, old)
            move_aside(old, new)
            if old is path:
                moved.append((path, new, problem))
        _CHECKED.pop(str(path), None)
    return moved


# ---- writing -----------------------------------------------------------------------------------
def write_row(sweep_dir: str | AnyPath, row: dict[str, Any], sweep_id: str) -> bool:
    """Write one finished cell. Returns False (and writes nothing) if the cell already has a file."""
    row = dict(row, sweep_id=sweep_id)
    table = row_table(row)  # validate before touching the disk
    return write_table_once(table, cell_path(sweep_dir, row["domain"], row["method"], row["cell_id"]))


def write_curve(sweep_dir: str | AnyPath, row: dict[str, Any], curve: list[dict[str, float]]) -> bool:
    """Write one cell's learning curve, before its row (the row is what marks the cell done).
    Same rule as rows: written once, atomically, never overwritten."""
    table = curve_table(row, curve)
    return write_table_once(table, curve_path(sweep_dir, row["domain"], row["method"], row["cell_id"]))


# ---- failures ----------------------------------------------------------------------------------
def _failure_path(sweep_dir: str | AnyPath, cell_id: str) -> AnyPath:
    return as_path(sweep_dir) / FAILED_DIR / f"{cell_id}.json"


def record_failure(sweep_dir: str | AnyPath, cell_id: str, domain: str, method: str, error: str) -> None:
    """Record a cell that kept failing; it stays out of the dataset and is retried on resume."""
    path = _failure_path(sweep_dir, cell_id)
    previous = _failure_record(path) if path.exists() else {}
    info = {"cell_id": cell_id, "domain": domain, "method": method, "error": error[-4000:],
            "failed_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "times_failed": _count(previous.get("times_failed")) + 1}
    write_replace(path, json.dumps(info, indent=1))


def clear_failure(sweep_dir: str | AnyPath, cell_id: str) -> None:
    _failure_path(sweep_dir, cell_id).unlink(missing_ok=True)


def failed_cells(sweep_dir: str | AnyPath) -> dict[str, dict[str, Any]]:
    """cell_id -> the failure record (cell_id, domain, method, error, failed_at, times_failed)."""
    root = as_path(sweep_dir) / FAILED_DIR
    if not isinstance(root, S3Path) and not root.is_dir():
        return {}
    return {p.stem: _failure_record(p) for p in sorted(root.glob("*.json")) if visible(p, root)}


def _count(value: Any) -> int:
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else 0


def _failure_record(path: AnyPath) -> dict[str, Any]:
    """A failure record as written by record_failure; one that is not (cut short, edited, planted) still says
    that its cell failed, with what is wrong with the record as its error, instead of stopping the reader."""
    try:
        record = json.loads(path.read_text())
        if isinstance(record, dict):
            return record
        problem = "is not a JSON object"
    except (ValueError, UnicodeDecodeError) as err:
        problem = f"cannot be read ({type(err).__name__})"
    return {"cell_id": path.stem, "error": f"the failure record {path.name} {problem}", "times_failed": 0}


def is_base_rejection(record: dict[str, Any]) -> bool:
    """Whether a failure record says the cell's base met no bar in its attempts (BaseRejected): a failure that
    a retry repeats, shared by every cell of the trial."""
    return last_error_line(record, width=100_000).startswith("BaseRejected")


def last_error_line(record: dict[str, Any], width: int = 160) -> str:
    """The last line of a failure record's error (the exception), for one-line listings."""
    lines = str(record.get("error", "")).strip().splitlines()
    return (lines[-1] if lines else "failed")[:width]


# ---- manifest ----------------------------------------------------------------------------------
def write_manifest(sweep_dir: str | AnyPath, manifest: dict[str, Any]) -> None:
    """Store the grid of a sweep. Its shape is the ledger's (asp_dist.sweep.ledger.new_manifest):
    name, space, grid_hash, cells (ids) and specs (resolved dicts, aligned with cells)."""
    write_replace(as_path(sweep_dir) / MANIFEST, json.dumps(manifest, indent=1, sort_keys=True))


def read_manifest(sweep_dir: str | AnyPath) -> dict[str, Any] | None:
    """The sweep's manifest, or None when it has none. A file that is not one is an error, not 'no grid'."""
    path = as_path(sweep_dir) / MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
    except ValueError as e:
        raise SchemaError(f"{path} is not valid JSON ({e}); it should hold the sweep's grid") from None
    cells = manifest.get("cells") if isinstance(manifest, dict) else None
    if not isinstance(cells, list) or not all(isinstance(c, str) for c in cells):
        raise SchemaError(f"{path} is not a sweep manifest: it needs a list of cell ids under 'cells'")
    return manifest


# ---- reading -----------------------------------------------------------------------------------
def read_table(sweep_dir: str | AnyPath, strict: bool = False) -> pa.Table:
    """All finished rows of a sweep as one Arrow table with the pinned schema (verified files only, see
    cell_files; `strict`: SchemaError on any file that is not a cell's)."""
    files = cell_files(sweep_dir, strict)
    if not files:
        return schema().empty_table()
    # Explicit schema: files written before a domain was added lack its metric columns -> null.
    return parquet_dataset(files, schema=schema()).to_table()


def _plain_partitions(df: pd.DataFrame) -> pd.DataFrame:
    """domain and method as plain strings (they are stored dictionary-encoded)."""
    for col in PARTITION_COLUMNS:
        df[col] = df[col].astype(str) if len(df) else df[col].astype(object)
    return df


def read_curves(sweep_dir: str | AnyPath) -> pd.DataFrame:
    """Every learning-curve point of a sweep (one row per cell and step), by cell id and step."""
    files = curve_files(sweep_dir)
    table = parquet_dataset(files, schema=curve_schema()).to_table() if files else curve_schema().empty_table()
    df = table.to_pandas()
    return _plain_partitions(df).sort_values(["cell_id", "step"], kind="stable").reset_index(drop=True)


def read_rows(sweep_dir: str | AnyPath, strict: bool = False) -> pd.DataFrame:
    """All finished rows of a sweep as a DataFrame (domain and method as plain strings), by cell id."""
    df = read_table(sweep_dir, strict).to_pandas()
    return _plain_partitions(df).sort_values("cell_id", kind="stable").reset_index(drop=True)
