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
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import pandas as pd
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from asp_dist.errors import SchemaError, SpecError
from asp_dist.results import store
from asp_dist.results.location import AnyPath, parquet_dataset, read_parquet_schema
from asp_dist.results.s3 import S3Path

KEY_COLUMNS = ("domain", "method", "paired", "trial")
DEFAULT_ORDER = ("domain", "method", "paired", "trial")
FORMATS = ("table", "csv", "json", "parquet")
STATS_DIR = "stats"  # the stats job's output tables inside a sweep or --out directory


@dataclass
class Inputs:
    """The Parquet files behind one or more inputs, and the sweep directories among the inputs."""

    files: list[AnyPath]  # local Paths or S3Paths (asp_dist.results.location, .s3)
    sweep_dirs: list[AnyPath] = field(default_factory=list)
    schema: pa.Schema | None = None

    def dataset(self) -> ds.Dataset:
        """A pyarrow dataset over exactly these files, read with the unified schema."""
        return parquet_dataset(self.files, schema=self.schema)


def _loose_files(path: AnyPath) -> list[AnyPath]:
    """Parquet files of a directory that is not a sweep (its top-level stats/ folder left out)."""
    return sorted(f for f in path.rglob("*.parquet")
                  if f.is_file() and store.visible(f, path) and f.relative_to(path).parts[0] != STATS_DIR)


def find_inputs(paths: Sequence[str | Path], results: str | Path = store.DEFAULT_RESULTS,
                curves: bool = False, strict: bool = False) -> Inputs:
    """The result files behind the given sweeps (names under `results`, or paths), directories or files;
    with `curves`, a sweep's learning curves instead of its cell rows. A sweep's cell files are verified
    by the store (store.cell_files): one that is not a cell's is left out with a warning, or with
    `strict` refused."""
    if not paths:
        raise SpecError("no input given: pass a sweep name or directory, a directory or .parquet files")
    files: list[AnyPath] = []
    sweeps: list[AnyPath] = []
    for raw in paths:
        path = store.locate_sweep(raw, results)
        if not path.exists():
            where = "an S3 prefix" if isinstance(path, S3Path) else "a sweep directory"
            raise SpecError(f"{path} does not exist; pass a sweep name (under --results {results}), "
                            f"{where} or .parquet files")
        if path.is_file():
            if path.suffix != ".parquet":
                raise SpecError(f"{path} is not a .parquet file")
            files.append(path)
        elif store.is_sweep_dir(path):
            sweeps.append(path)
            files.extend(store.curve_files(path) if curves else store.cell_files(path, strict))
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


def unified_schema(files: Sequence[AnyPath]) -> pa.Schema:
    """One schema for all files, or SchemaError naming the first column that cannot be unified.

    Null-typed columns (all values missing in a file) take the other files' type; integers
    and floats widen to float; every other disagreement is refused."""
    kinds: dict[str, tuple[str, AnyPath]] = {}
    order: list[str] = []
    for f in files:
        try:
            schema = read_parquet_schema(f)
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
                curves: bool = False, strict: bool = False) -> Inputs:
    """find_inputs, and the one schema their files are read with (SchemaError when they disagree)."""
    inputs = find_inputs(paths, results, curves, strict)
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

def connect(inputs: Inputs, view: str = "cells"):
    """A DuckDB connection that can read the inputs' rows and nothing else.

    Read-only by construction, not by inspecting the user's SQL: the rows are read into an Arrow
    table here (pyarrow, with the unified schema), registered on a fresh in-memory connection as
    ``view`` (``cells`` or ``curves``), and then the connection is cut off from the outside world —
    no file, network or extension access (so COPY ... TO, ATTACH, INSTALL/LOAD, EXPORT DATABASE and
    read_csv('/etc/passwd') fail), no Python objects found by name, no spilling to a temp
    directory — and its configuration is locked, so no SET or PRAGMA can undo any of it.
    Whatever SQL then runs can only read the registered rows and create in-memory objects that
    vanish with the connection."""
    import duckdb

    if inputs.schema is None:
        inputs.schema = unified_schema(inputs.files)
    table = inputs.dataset().to_table()
    keys = [k for k in (*DEFAULT_ORDER, "step") if k in table.column_names]
    table = table.sort_by([(k, "ascending") for k in keys])  # rows in key order unless the SQL says otherwise
    con = duckdb.connect(":memory:", config={"threads": 1})  # CPU is shared; queries over a sweep are small
    con.register(view, table)
    for setting in ("temp_directory = ''", "enable_external_access = false", "python_enable_replacements = false",
                    "allow_community_extensions = false", "autoinstall_known_extensions = false",
                    "autoload_known_extensions = false", "lock_configuration = true"):
        con.execute(f"SET {setting}")  # the order matters: temp_directory cannot change once external access is off
    return con


def _duckdb_error(err: Exception, what: str) -> SpecError:
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return SpecError(f"{what}: {first}")


def check_sql(con, sql: str) -> None:
    """One SELECT statement, or SpecError. DuckDB's own parser splits and classifies the text
    (``extract_statements``): no hand-written check of quotes, comments or semicolons to get wrong.
    DESCRIBE and SUMMARIZE are SELECTs; COPY, ATTACH, INSTALL, LOAD, PRAGMA, SET, CREATE ... are not."""
    import duckdb

    try:
        statements = con.extract_statements(sql)
    except duckdb.Error as err:
        raise _duckdb_error(err, "SQL query failed") from None
    if len(statements) != 1:
        raise SpecError(f"--sql takes exactly one SELECT statement, got {len(statements) or 'none'}"
                        + ("; run the statements one at a time" if len(statements) > 1 else ""))
    kind = statements[0].type
    if kind != duckdb.StatementType.SELECT:
        raise SpecError(f"--sql runs read-only SELECT queries (or DESCRIBE/SUMMARIZE); this is a {kind.name} "
                        f"statement")


def where_expression(where: str):
    """`--where` parsed as exactly one SQL expression (duckdb.SQLExpression), never pasted into query text:
    the parser refuses a second expression, a `;`, a closing parenthesis that escapes the WHERE, ORDER BY or
    LIMIT, so the filter can only be a boolean condition on the rows (subqueries in it read the same view).
    The expression goes into the query as a parsed object through the relational API (run_query).

    DuckDB releases without SQLExpression get the next best check: ``SELECT * FROM t WHERE (<expr>)`` must be
    exactly one SELECT statement by DuckDB's own parser (extract_statements) — that stops a `;` and any
    non-SELECT, though not a `) UNION SELECT ...` inside it, which the read-only connection makes harmless."""
    import duckdb

    if not where.strip():
        raise SpecError("--where is empty; give a SQL condition such as \"method = 'asp'\" or leave it out")
    if hasattr(duckdb, "SQLExpression"):
        try:
            return duckdb.SQLExpression(where)
        except duckdb.Error as err:
            raise _duckdb_error(err, f"--where {where!r} is not one SQL condition") from None
    text = f"SELECT * FROM t WHERE ({where}\n)"  # the newline ends a trailing -- comment before the parenthesis
    try:
        statements = duckdb.connect().extract_statements(text)
    except duckdb.Error as err:
        raise _duckdb_error(err, f"--where {where!r} is not one SQL condition") from None
    if len(statements) != 1 or statements[0].type != duckdb.StatementType.SELECT:
        raise SpecError(f"--where {where!r} is not one SQL condition")
    return f"({where}\n)"


def check_columns(wanted: Sequence[str], available: Sequence[str]) -> None:
    for col in wanted:
        if col not in available:
            near = difflib.get_close_matches(col, available, n=3)
            hint = f"; did you mean {', '.join(near)}?" if near else "; `--sql 'DESCRIBE cells'` lists the columns"
            raise SpecError(f"unknown column {col!r}{hint}")


def run_query(paths: Sequence[str | Path], where: str | None = None, columns: Sequence[str] | None = None,
              sql: str | None = None, limit: int | None = None,
              results: str | Path = store.DEFAULT_RESULTS, curves: bool = False) -> pd.DataFrame:
    """Rows of the input(s) matching a SQL WHERE expression, or the result of one SELECT statement on the
    view `cells` (or `curves`: the sweeps' learning curves, with `curves`). Reads only: see `connect`."""
    import duckdb

    if sql is not None and (where is not None or columns or limit is not None):
        raise SpecError("--sql is a whole query; put the filter, the columns and any LIMIT inside it "
                        "instead of --where/--columns/--limit")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 0):
        raise SpecError(f"--limit must be an integer >= 0, got {limit!r}")
    expression = where_expression(where) if where is not None else None
    inputs = open_inputs(paths, results, curves)
    view = "curves" if curves else "cells"
    con = connect(inputs, view)
    try:
        if sql is not None:
            check_sql(con, sql)
            try:
                df = con.execute(sql).df()
            except Exception as err:  # duckdb raises many exception classes, all user errors here
                raise _duckdb_error(err, "SQL query failed") from None
        else:
            names = inputs.schema.names
            cols = list(columns) if columns else list(names)
            check_columns(cols, names)
            try:  # the relational API binds (and may fail) at each step, not only at .df()
                rel = con.table(view)
                if expression is not None:
                    rel = rel.filter(expression)
                rel = rel.order(", ".join(f'"{k}"' for k in (*DEFAULT_ORDER, "step") if k in names))
                rel = rel.select(*[duckdb.ColumnExpression(c) for c in cols])
                if limit is not None:
                    rel = rel.limit(limit)
                df = rel.df()
            except Exception as err:
                raise _duckdb_error(err, f"--where {where!r} failed" if where is not None else "query failed") \
                    from None
    finally:
        con.close()
    return df


# ---- output -------------------------------------------------------------------------------------

def sweep_containing(path: str | Path) -> Path | None:
    """The sweep directory (store.is_sweep_dir) that `path` lies in, walking up its parents, or None.
    Both the path as written (made absolute) and with symlinks resolved are checked."""
    absolute = Path(os.path.abspath(Path(path).expanduser()))
    for candidate in (absolute, absolute.resolve()):
        for parent in candidate.parents:
            if store.is_sweep_dir(parent):
                return parent
    return None


def check_output_file(out: str | Path, force: bool = False, what: str = "--out") -> Path:
    """Refuse an output file that would overwrite something without `force`, or land inside a sweep's tree;
    checked before any work is done, and nothing is created."""
    path = Path(out).expanduser()
    if not str(out).strip():
        raise SpecError(f"{what} is empty; name the file to write")
    inside = sweep_containing(path)
    if inside is not None:
        raise SpecError(f"{what} {out} lies inside the sweep {inside}; a sweep's tree is written only by the "
                        f"sweep itself — choose a path outside it")
    if path.is_dir():
        raise SpecError(f"{what} {out} is a directory; name a file")
    if (path.exists() or path.is_symlink()) and not force:
        raise SpecError(f"{what} {out} already exists; pass --force to overwrite it")
    parent = path.parent
    if not parent.is_dir():
        raise SpecError(f"cannot write {what} {out}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise SpecError(f"cannot write {what} {out}: directory {parent} is not writable")
    return path


def write_result(df: pd.DataFrame, fmt: str = "table", out: str | Path | None = None, force: bool = False) -> None:
    """Write a query result in the chosen format to `out` (or stdout; parquet needs `out`). A file is
    written whole or not at all (temp file + link/rename); an existing one only with `force`."""
    if fmt not in FORMATS:
        raise SpecError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt == "parquet" and out is None:
        raise SpecError("--format parquet needs --out FILE")
    text = ""
    if fmt == "table":
        text = df.to_string(index=False) + "\n" if len(df) else "(no rows)\n"
    elif fmt == "csv":
        text = df.to_csv(index=False)
    elif fmt == "json":
        text = df.to_json(orient="records", lines=True, date_format="iso")
    if out is None:
        sys.stdout.write(text)
        return
    path = check_output_file(out, force)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)  # mkstemp's 0600 would hide the result from the user's group
            with os.fdopen(fd, "wb") as fh:
                if fmt == "parquet":
                    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), fh)
                else:
                    fh.write(text.encode())
            if force:
                os.replace(tmp, path)
            else:
                try:
                    os.link(tmp, path)  # never overwrites, even a file that appeared since the check
                except FileExistsError:
                    raise SpecError(f"--out {out} already exists; pass --force to overwrite it") from None
                except OSError:  # a file system without hard links (as asp_dist.fsutil)
                    if path.exists():
                        raise SpecError(f"--out {out} already exists; pass --force to overwrite it") from None
                    os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError as e:  # a read-only or full file system
        raise SpecError(f"cannot write --out {out}: {e.strerror or e}") from None
