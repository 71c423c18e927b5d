"""Ad-hoc reading of result rows from several sources, and queries over them (`asp-dist query`).

Accepted inputs, alone or mixed: a sweep (a directory or a bare name under ``--results``; its
finished cells are listed by asp_dist.results.store, which owns the sweep layout), any other
directory of Parquet files (read recursively, leaving out a ``stats/`` folder directly inside
it: the stats job's own tables), or single ``.parquet`` files such as the merged datasets in
results/examples/. Their schemas are checked to agree (they need not be the pinned row schema:
merged or older files are read too), then the rows go to pandas (the stats job), to
pyarrow.dataset, or to DuckDB as a view named ``cells`` (``--sql``).
"""

from __future__ import annotations

import difflib
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import pandas as pd
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from asp_dist.errors import SchemaError, SpecError
from asp_dist.results import store

KEY_COLUMNS = ("domain", "method", "paired", "trial")
DEFAULT_ORDER = ("domain", "method", "paired", "trial")
FORMATS = ("table", "csv", "json", "parquet")
STATS_DIR = "stats"  # the stats job's output tables inside a sweep or --out directory


@dataclass
class Inputs:
    """The Parquet files behind one or more inputs, and the sweep directories among the inputs."""

    files: list[Path]
    sweep_dirs: list[Path] = field(default_factory=list)
    schema: pa.Schema | None = None

    def dataset(self) -> ds.Dataset:
        """A pyarrow dataset over exactly these files, read with the unified schema."""
        return ds.dataset([str(f) for f in self.files], schema=self.schema, format="parquet")


def _loose_files(path: Path) -> list[Path]:
    """Parquet files of a directory that is not a sweep (its top-level stats/ folder left out)."""
    return sorted(f for f in path.rglob("*.parquet")
                  if f.is_file() and store.visible(f, path) and f.relative_to(path).parts[0] != STATS_DIR)


def find_inputs(paths: Sequence[str | Path], results: str | Path = store.DEFAULT_RESULTS,
                curves: bool = False) -> Inputs:
    """The result files behind the given sweeps (names under `results`, or paths), directories or files;
    with `curves`, a sweep's learning curves instead of its cell rows."""
    if not paths:
        raise SpecError("no input given: pass a sweep name or directory, a directory or .parquet files")
    files: list[Path] = []
    sweeps: list[Path] = []
    for raw in paths:
        path = store.locate_sweep(raw, results)
        if not path.exists():
            raise SpecError(f"{path} does not exist; pass a sweep name (under --results {results}), "
                            f"a sweep directory or .parquet files")
        if path.is_file():
            if path.suffix != ".parquet":
                raise SpecError(f"{path} is not a .parquet file")
            files.append(path)
        elif store.is_sweep_dir(path):
            sweeps.append(path)
            files.extend(store.curve_files(path) if curves else store.cell_files(path))
        else:
            files.extend(_loose_files(path))
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
    """One schema for all files, or SchemaError naming the first column that cannot be unified.

    Null-typed columns (all values missing in a file) take the other files' type; integers
    and floats widen to float; every other disagreement is refused."""
    kinds: dict[str, tuple[str, Path]] = {}
    order: list[str] = []
    for f in files:
        try:
            schema = pq.read_schema(f)
        except (pa.ArrowException, OSError) as err:
            raise SchemaError(f"cannot read {f}: {err}") from None
        missing = [k for k in KEY_COLUMNS if k not in schema.names]
        if missing:
            raise SchemaError(f"{f} lacks the key column(s) {', '.join(missing)}; it is not a cell result row "
                              f"(expected columns {', '.join(KEY_COLUMNS)})")
        for fld in schema:
            kind = _kind(fld.type)
            if kind not in _CANONICAL:
                raise SchemaError(f"column {fld.name!r} in {f} has unsupported type {fld.type}")
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
                raise SchemaError(f"schema mismatch: column {fld.name!r} is {seen} in {where} but {kind} in {f}; "
                                  "these files come from different code versions or tools, read them separately")
    for key, numeric in (("paired", True), ("trial", True), ("domain", False), ("method", False)):
        kind, where = kinds[key]
        if (kind in ("int", "float")) != numeric and kind != "null":
            expected = "an integer" if numeric else "text"
            raise SchemaError(f"key column {key!r} is {kind} in {where}; expected {expected}")
    return pa.schema([(name, _CANONICAL[kinds[name][0]]) for name in order])


def open_inputs(paths: Sequence[str | Path], results: str | Path = store.DEFAULT_RESULTS,
                curves: bool = False) -> Inputs:
    """find_inputs, and the one schema their files are read with (SchemaError when they disagree)."""
    inputs = find_inputs(paths, results, curves)
    inputs.schema = unified_schema(inputs.files)
    return inputs


def load_rows(paths: Sequence[str | Path] | Inputs, results: str | Path = store.DEFAULT_RESULTS) -> pd.DataFrame:
    """All rows of the given inputs as one DataFrame (schema-checked), sorted by the key columns."""
    inputs = paths if isinstance(paths, Inputs) else open_inputs(paths, results)
    if inputs.schema is None:
        inputs.schema = unified_schema(inputs.files)
    table = inputs.dataset().to_table()
    df = table.to_pandas()
    return df.sort_values(list(DEFAULT_ORDER), kind="stable").reset_index(drop=True)


# ---- queries ------------------------------------------------------------------------------------

def _sql_literal_list(files: Iterable[Path]) -> str:
    return "[" + ", ".join("'" + str(f).replace("'", "''") + "'" for f in files) + "]"


def connect(inputs: Inputs, view: str = "cells"):
    """A DuckDB connection with a view (``cells``, or ``curves``) over exactly the inputs' files."""
    import duckdb

    con = duckdb.connect()
    con.execute("SET threads TO 1")  # CPU is shared; queries over a sweep are small
    files = _sql_literal_list(inputs.files)
    con.execute(f"CREATE VIEW {view} AS SELECT * FROM read_parquet({files}, union_by_name = true)")
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
              sql: str | None = None, limit: int | None = None,
              results: str | Path = store.DEFAULT_RESULTS, curves: bool = False) -> pd.DataFrame:
    """Rows of the input(s) matching a SQL WHERE expression, or the result of a full SQL query on the
    view `cells` (or `curves`: the sweeps' learning curves, with `curves`)."""
    inputs = open_inputs(paths, results, curves)
    view = "curves" if curves else "cells"
    if sql and (where or columns):
        raise SpecError("--sql is a whole query; put the filter and the columns inside it instead of --where/--columns")
    con = connect(inputs, view)
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
            order = ", ".join(k for k in (*DEFAULT_ORDER, "step") if k in names)
            query = f"SELECT {select} FROM {view}" + (f" WHERE {where}" if where else "") + f" ORDER BY {order}"
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
    if fmt == "parquet" and out is None:
        raise SpecError("--format parquet needs --out FILE")
    if fmt == "table":
        text = df.to_string(index=False) + "\n" if len(df) else "(no rows)\n"
    elif fmt == "csv":
        text = df.to_csv(index=False)
    elif fmt == "json":
        text = df.to_json(orient="records", lines=True, date_format="iso")
    if out is None:
        sys.stdout.write(text)
        return
    try:
        if fmt == "parquet":
            pq.write_table(pa.Table.from_pandas(df, preserve_index=False), out)
        else:
            Path(out).write_text(text)
    except OSError as e:  # a missing or read-only directory: the user's --out
        raise SpecError(f"cannot write --out {out}: {e.strerror or e}") from None
