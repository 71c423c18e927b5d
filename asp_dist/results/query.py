"""Reading a sweep's result rows, and ad-hoc queries over them (`asp-dist query`).

A sweep directory ``results/<sweep>/`` holds one Parquet file per finished cell under
``cells/`` (nested ``domain=…/method=…`` folders). This module finds those files itself
(no dependency on the sweep service's reader), checks that their schemas agree, and gives
the rows to pandas (the stats job), to pyarrow.dataset, or to DuckDB as a view named
``cells`` (``--sql``).

Accepted inputs, alone or mixed: a sweep directory (its ``cells/`` is read), any directory
of Parquet files (read recursively), or single ``.parquet`` files. Names that start with
``.`` or ``_`` are temp files of an unfinished write and are ignored, and so is a ``stats/``
folder directly inside a given directory (the stats job's own output tables).
"""

from __future__ import annotations

import difflib
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import pandas as pd
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from asp_dist.spec import SpecError

KEY_COLUMNS = ("domain", "method", "paired", "trial")
DEFAULT_ORDER = ("domain", "method", "paired", "trial")
FORMATS = ("table", "csv", "json", "parquet")


class SchemaMismatch(SpecError):
    """Result files whose columns cannot be read as one table."""


@dataclass
class Inputs:
    """The Parquet files behind one or more sweeps, and the sweep directories among the inputs."""

    files: list[Path]
    sweep_dirs: list[Path] = field(default_factory=list)
    schema: pa.Schema | None = None

    def dataset(self) -> ds.Dataset:
        """A pyarrow dataset over exactly these files, read with the unified schema."""
        return ds.dataset([str(f) for f in self.files], schema=self.schema, format="parquet")


def _visible(path: Path, root: Path) -> bool:
    parts = path.relative_to(root).parts
    return not any(p.startswith((".", "_")) for p in parts)


def locate_sweep(name_or_path: str | Path) -> Path:
    """A path as given, or results/<name> for a bare sweep name (as `asp-dist status NAME` takes)."""
    path = Path(name_or_path)
    if not path.exists() and (Path("results") / path).is_dir():
        return Path("results") / path
    return path


def cell_files(paths: Sequence[str | Path]) -> Inputs:
    """List the result files behind the given sweep directories, directories or files."""
    if not paths:
        raise SpecError("no input given: pass a sweep directory (results/<sweep>), a directory or .parquet files")
    files: list[Path] = []
    sweeps: list[Path] = []
    for raw in paths:
        path = locate_sweep(raw)
        if not path.exists():
            raise SpecError(f"{path} does not exist; pass a sweep name, or a directory such as results/<sweep>")
        if path.is_file():
            if path.suffix != ".parquet":
                raise SpecError(f"{path} is not a .parquet file")
            files.append(path)
            continue
        root = path / "cells" if (path / "cells").is_dir() else path
        if root != path:
            sweeps.append(path)
        found = sorted(f for f in root.rglob("*.parquet")
                       if _visible(f, root) and f.is_file() and not (root == path and f.relative_to(root).parts[0] == "stats"))
        files.extend(found)
    unique = list(dict.fromkeys(f.resolve() for f in files))
    if not unique:
        raise SpecError(f"no finished cells (*.parquet) found under {', '.join(map(str, paths))}")
    return Inputs(unique, sweeps)


# ---- schema checking ----------------------------------------------------------------------------

def _kind(t: pa.DataType) -> str:
    if pa.types.is_null(t):
        return "null"
    if pa.types.is_boolean(t):
        return "bool"
    if pa.types.is_integer(t):
        return "int"
    if pa.types.is_floating(t):
        return "float"
    if pa.types.is_string(t) or pa.types.is_large_string(t) or pa.types.is_string_view(t):
        return "string"
    if pa.types.is_dictionary(t):
        return _kind(t.value_type)
    return str(t)


_CANONICAL = {"bool": pa.bool_(), "int": pa.int64(), "float": pa.float64(), "string": pa.string(), "null": pa.null()}


def unified_schema(files: Sequence[Path]) -> pa.Schema:
    """One schema for all files, or SchemaMismatch naming the first column that cannot be unified.

    Null-typed columns (all values missing in a file) take the other files' type; integers
    and floats widen to float; every other disagreement is refused."""
    kinds: dict[str, tuple[str, Path]] = {}
    order: list[str] = []
    for f in files:
        try:
            schema = pq.read_schema(f)
        except (pa.ArrowException, OSError) as err:
            raise SchemaMismatch(f"cannot read {f}: {err}") from None
        missing = [k for k in KEY_COLUMNS if k not in schema.names]
        if missing:
            raise SchemaMismatch(f"{f} lacks the key column(s) {', '.join(missing)}; it is not a cell result row "
                                 f"(expected columns {', '.join(KEY_COLUMNS)})")
        for fld in schema:
            kind = _kind(fld.type)
            if kind not in _CANONICAL:
                raise SchemaMismatch(f"column {fld.name!r} in {f} has unsupported type {fld.type}")
            if fld.name not in kinds:
                kinds[fld.name] = (kind, f)
                order.append(fld.name)
                continue
            seen, where = kinds[fld.name]
            if kind == seen or kind == "null":
                continue
            if seen == "null":
                kinds[fld.name] = (kind, f)
            elif {seen, kind} == {"int", "float"}:
                kinds[fld.name] = ("float", f)
            else:
                raise SchemaMismatch(f"schema mismatch: column {fld.name!r} is {seen} in {where} but {kind} in {f}; "
                                     "these files come from different code versions or tools, read them separately")
    for key, numeric in (("paired", True), ("trial", True), ("domain", False), ("method", False)):
        kind, where = kinds[key]
        if (kind in ("int", "float")) != numeric and kind != "null":
            raise SchemaMismatch(f"key column {key!r} is {kind} in {where}; expected {'an integer' if numeric else 'text'}")
    return pa.schema([(name, _CANONICAL[kinds[name][0]]) for name in order])


def open_inputs(paths: Sequence[str | Path]) -> Inputs:
    inputs = cell_files(paths)
    inputs.schema = unified_schema(inputs.files)
    return inputs


def load_rows(paths: Sequence[str | Path] | Inputs) -> pd.DataFrame:
    """All rows of the given sweeps as one DataFrame (schema-checked), sorted by the key columns."""
    inputs = paths if isinstance(paths, Inputs) else open_inputs(paths)
    if inputs.schema is None:
        inputs.schema = unified_schema(inputs.files)
    table = inputs.dataset().to_table()
    df = table.to_pandas()
    return df.sort_values(list(DEFAULT_ORDER), kind="stable").reset_index(drop=True)


def read_manifest_ids(sweep_dir: Path) -> list[str] | None:
    """Cell ids of the planned grid from ``manifest.json``, read defensively (None if absent or unreadable).

    Accepts {"cells": [ids] | {id: spec} | [{"cell_id": ...}]}, {"cell_ids": [...]}, or a bare list."""
    path = Path(sweep_dir) / "manifest.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if isinstance(data, dict):
        for key in ("cells", "cell_ids", "grid", "expected"):
            if key in data:
                data = data[key]
                break
        else:
            return None
    if isinstance(data, dict):
        return [str(k) for k in data]
    if isinstance(data, list):
        ids = []
        for item in data:
            if isinstance(item, str):
                ids.append(item)
            elif isinstance(item, dict) and "cell_id" in item:
                ids.append(str(item["cell_id"]))
        return ids
    return None


# ---- queries ------------------------------------------------------------------------------------

def _sql_literal_list(files: Iterable[Path]) -> str:
    return "[" + ", ".join("'" + str(f).replace("'", "''") + "'" for f in files) + "]"


def connect(inputs: Inputs):
    """A DuckDB connection with a view ``cells`` over exactly the inputs' files."""
    import duckdb

    con = duckdb.connect()
    con.execute("SET threads TO 1")  # CPU is shared; queries over a sweep are small
    con.execute(f"CREATE VIEW cells AS SELECT * FROM read_parquet({_sql_literal_list(inputs.files)}, union_by_name = true)")
    return con


def _duckdb_error(err: Exception, what: str) -> SpecError:
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return SpecError(f"{what}: {first}")


def check_columns(wanted: Sequence[str], available: Sequence[str]) -> None:
    for col in wanted:
        if col not in available:
            near = difflib.get_close_matches(col, available, n=3)
            hint = f"; did you mean {', '.join(near)}?" if near else "; `--sql 'DESCRIBE cells'` lists the columns"
            raise SpecError(f"unknown column {col!r}{hint}")


def run_query(paths: Sequence[str | Path], where: str | None = None, columns: Sequence[str] | None = None,
              sql: str | None = None, limit: int | None = None) -> pd.DataFrame:
    """Rows of the sweep(s) matching a SQL WHERE expression, or the result of a full SQL query on `cells`."""
    inputs = open_inputs(paths)
    if sql and (where or columns):
        raise SpecError("--sql is a whole query; put the filter and the columns inside it instead of --where/--columns")
    con = connect(inputs)
    try:
        if sql:
            try:
                df = con.execute(sql).df()
            except Exception as err:  # duckdb raises many exception classes, all user errors here
                raise _duckdb_error(err, "SQL query failed") from None
        else:
            names = inputs.schema.names
            cols = list(columns) if columns else list(names)
            check_columns(cols, names)
            select = ", ".join('"' + c.replace('"', '""') + '"' for c in cols)
            order = ", ".join(k for k in DEFAULT_ORDER if k in names)
            query = f"SELECT {select} FROM cells" + (f" WHERE {where}" if where else "") + f" ORDER BY {order}"
            if limit is not None:
                query += f" LIMIT {int(limit)}"
            try:
                df = con.execute(query).df()
            except Exception as err:
                raise _duckdb_error(err, f"--where {where!r} failed") from None
    finally:
        con.close()
    return df


def write_result(df: pd.DataFrame, fmt: str = "table", out: str | Path | None = None) -> None:
    """Write a query result in the chosen format to `out` (or stdout; parquet needs `out`)."""
    if fmt not in FORMATS:
        raise SpecError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt == "parquet":
        if out is None:
            raise SpecError("--format parquet needs --out FILE")
        pq.write_table(pa.Table.from_pandas(df, preserve_index=False), out)
        return
    if fmt == "table":
        text = df.to_string(index=False) + "\n" if len(df) else "(no rows)\n"
    elif fmt == "csv":
        text = df.to_csv(index=False)
    else:
        text = df.to_json(orient="records", lines=True, date_format="iso")
    if out is None:
        sys.stdout.write(text)
    else:
        Path(out).write_text(text)
