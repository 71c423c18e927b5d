"""`asp-dist query` is read-only by construction: its SQL runs on a connection that holds the sweep's rows
(an Arrow table) and can reach nothing else — no files, extensions, settings or Python objects — and
`--out` never overwrites a file without --force nor writes inside a sweep's tree."""

from __future__ import annotations

import os

import pandas as pd
import pytest
from harness import finished_row
from test_stats import make_rows, write_sweep

from asp_dist.cli import main
from asp_dist.errors import SpecError
from asp_dist.results.query import check_output_file, connect, open_inputs, run_query, sweep_containing


@pytest.fixture
def sweep(tmp_path):
    return write_sweep(tmp_path / "results" / "q", make_rows(trials=range(2)), manifest_ids=[])


def tree(root):
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def one_line_error(capsys, argv, needle=""):
    code = main(argv)
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert code == 2, captured.err
    assert len(lines) == 1 and lines[0].startswith("asp-dist: error: "), captured.err
    assert needle in lines[0], lines[0]
    assert "Traceback" not in captured.err
    return lines[0]


# ---- the connection itself: even SQL that skipped every check can only read the rows ---------------------

def test_the_connection_reaches_nothing_but_the_rows(sweep, tmp_path):
    import duckdb

    secret_table = pd.DataFrame({"x": [42]})  # noqa: F841 - a Python object DuckDB would find by name
    con = connect(open_inputs([sweep]))
    try:
        assert con.execute("SELECT count(*) FROM cells").fetchone()[0] == 24
        target = tmp_path / "leak.csv"
        refused = [
            f"COPY (SELECT * FROM cells) TO '{target}'",
            f"COPY cells TO '{target}' (FORMAT parquet)",
            f"ATTACH '{tmp_path / 'x.db'}' AS x",
            "INSTALL httpfs", "LOAD httpfs",  # (LOAD of a built-in such as parquet is a no-op; the CLI refuses it)
            "SELECT * FROM read_csv('/etc/passwd')", "SELECT * FROM read_text('/etc/passwd')",
            f"SELECT * FROM read_parquet('{next((sweep / 'cells').rglob('*.parquet'))}')",
            "SELECT * FROM glob('/etc/*')", f"EXPORT DATABASE '{tmp_path / 'export'}'",
            "SET enable_external_access = true", "RESET enable_external_access", "SET lock_configuration = false",
            "SET threads = 2", "PRAGMA threads = 2", "SET temp_directory = '/tmp'",
            "SELECT * FROM secret_table",
        ]
        for sql in refused:
            with pytest.raises(duckdb.Error):
                con.execute(sql).fetchall()
        assert con.execute("SELECT current_setting('enable_external_access')").fetchone()[0] is False
    finally:
        con.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"], "something was written"


# ---- the CLI: every write, attach, install, load, pragma or second statement is one line, exit 2 --------

@pytest.mark.parametrize("sql, needle", [
    ("COPY (SELECT * FROM cells) TO '{t}/x.csv'", "COPY statement"),
    ("COPY cells TO '{t}/x.parquet' (FORMAT parquet)", "COPY statement"),
    ("ATTACH '{t}/x.db' AS x", "ATTACH statement"),
    ("INSTALL httpfs", "LOAD statement"),
    ("LOAD httpfs", "LOAD statement"),
    ("PRAGMA threads = 4", "statement"),
    ("PRAGMA show_tables", "PRAGMA statement"),
    ("SET threads = 4", "SET statement"),
    ("CREATE TABLE t AS SELECT * FROM cells", "CREATE statement"),
    ("EXPORT DATABASE '{t}/export'", "EXPORT statement"),
    ("SELECT 1; COPY (SELECT * FROM cells) TO '{t}/x.csv'", "exactly one SELECT statement, got 2"),
    ("SELECT 1; SELECT 2", "exactly one SELECT statement, got 2"),
    ("", "exactly one SELECT statement, got none"),
    ("-- only a comment", "exactly one SELECT statement, got none"),
    ("SELECT * FROM read_csv('/etc/passwd')", "Permission Error"),
    ("SELECT * FROM read_parquet('{t}/results/q/cells/**/*.parquet')", "Permission Error"),
    ("SELECT * FROM cells WHERE paired IN (SELECT 1 FROM read_text('/etc/passwd'))", "Permission Error"),
])
def test_sql_that_is_not_one_read_only_select_is_refused(capsys, sweep, tmp_path, sql, needle):
    before = tree(tmp_path)
    one_line_error(capsys, ["query", str(sweep), "--sql", sql.format(t=tmp_path)], needle)
    assert tree(tmp_path) == before


@pytest.mark.parametrize("where, needle", [
    ("1=1; COPY (SELECT * FROM cells) TO '{t}/x.csv'", "is not one SQL condition"),
    ("1=1) UNION SELECT * FROM cells --", "is not one SQL condition"),
    ("paired = 1 ORDER BY trial", "is not one SQL condition"),
    ("paired = 1 LIMIT 1", "is not one SQL condition"),
    ("paired = 1, trial = 0", "is not one SQL condition"),
    ("   ", "--where is empty"),
    ("EXISTS (SELECT * FROM read_csv('/etc/passwd'))", "Permission Error"),
    ("methd = 'asp'", "--where"),
])
def test_where_is_one_expression_not_pasted_text(capsys, sweep, tmp_path, where, needle):
    before = tree(tmp_path)
    one_line_error(capsys, ["query", str(sweep), "--where", where.format(t=tmp_path)], needle)
    assert tree(tmp_path) == before


def test_read_only_queries_still_work(sweep):
    assert run_query([sweep], sql="DESCRIBE cells")["column_name"].tolist()[:2] == ["domain", "method"]
    assert len(run_query([sweep], sql="SUMMARIZE cells")) > 0
    df = run_query([sweep], where="paired IN (SELECT max(paired) FROM cells) AND method = 'asp'",
                   columns=["method", "paired", "trial"])
    assert df.values.tolist() == [["asp", 4, 0], ["asp", 4, 1]]
    df = run_query([sweep], where="method = 'a;b' OR method = 'pc' -- a comment", columns=["method"], limit=3)
    assert df["method"].tolist() == ["pc"] * 3
    keys = run_query([sweep], columns=["method", "paired", "trial"])
    assert keys.values.tolist() == sorted(keys.values.tolist())  # ordered by the key columns
    with pytest.raises(SpecError, match="--sql is a whole query"):
        run_query([sweep], sql="SELECT 1", limit=2)


# ---- --out: never over an existing file without --force, never inside a sweep ----------------------------

def test_out_refuses_an_existing_file_unless_forced(capsys, sweep, tmp_path):
    out = tmp_path / "rows.csv"
    out.write_text("precious")
    one_line_error(capsys, ["query", str(sweep), "--format", "csv", "--out", str(out)], "pass --force")
    assert out.read_text() == "precious"
    assert main(["query", str(sweep), "--format", "csv", "--columns", "method", "--out", str(out), "--force"]) == 0
    assert out.read_text().splitlines()[0] == "method" and len(out.read_text().splitlines()) == 25
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temp file left behind"
    fresh = tmp_path / "new.parquet"
    assert main(["query", str(sweep), "--format", "parquet", "--out", str(fresh)]) == 0
    assert len(pd.read_parquet(fresh)) == 24
    umask = os.umask(0)
    os.umask(umask)
    assert fresh.stat().st_mode & 0o777 == 0o666 & ~umask  # as a plain open() would leave it, not mkstemp's 0600


@pytest.mark.parametrize("where", ["manifest.json", "rows.csv", "cells/rows.csv", "cells/domain=signaling/x.parquet",
                                   "stats/new-dir/rows.csv", "cells"])
def test_out_is_never_inside_a_sweep(capsys, sweep, tmp_path, where):
    before = tree(tmp_path)
    out = sweep / where
    line = one_line_error(capsys, ["query", str(sweep), "--out", str(out), "--force"], "")
    assert "inside the sweep" in line or "is a directory" in line
    assert tree(tmp_path) == before


def test_out_through_a_symlink_into_a_sweep_is_refused(capsys, sweep, tmp_path):
    link = tmp_path / "elsewhere"
    link.symlink_to(sweep / "cells")
    assert sweep_containing(link / "rows.csv") == sweep
    before = tree(sweep)
    one_line_error(capsys, ["query", str(sweep), "--out", str(link / "rows.csv")], "inside the sweep")
    assert tree(sweep) == before
    assert sweep_containing(tmp_path / "rows.csv") is None


def test_check_output_file_creates_nothing(tmp_path):
    with pytest.raises(SpecError, match="does not exist"):
        check_output_file(tmp_path / "no" / "such" / "x.csv")
    assert list(tmp_path.iterdir()) == []
    assert check_output_file(tmp_path / "x.csv") == tmp_path / "x.csv"
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(SpecError, match="not writable"):
            check_output_file(ro / "x.csv")


# ---- THE reader counts only files that are a cell's: stray, planted and truncated files are named -------

@pytest.fixture
def planted(tmp_path):
    """A sweep 'exp' (smoke grid) with two genuine cells and five files that are not what they claim."""
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    from asp_dist.results import store
    from asp_dist.sweep.ledger import new_manifest
    from asp_dist.sweep.spaces import expand

    specs = expand("smoke")
    sweep = tmp_path / "results" / "exp"
    store.write_manifest(sweep, new_manifest("exp", "smoke", specs))
    genuine = []
    for spec in specs[:2]:
        store.write_row(sweep, finished_row(spec), sweep_id="exp")
        genuine.append(store.cell_path(sweep, spec.domain, spec.method, spec.cell_id))
    first, other = genuine[0], specs[2]
    cells = store.cells_dir(sweep)
    bad = {
        "stray": cells / "stray.parquet",
        "renamed": first.parent / f"{other.cell_id}.parquet",
        "moved": cells / "domain=signaling" / "method=zzz" / first.name,
        "truncated": store.cell_path(sweep, other.domain, specs[3].method, specs[3].cell_id),
        "two rows": store.cell_path(sweep, specs[4].domain, specs[4].method, specs[4].cell_id),
    }
    shutil.copy(first, bad["stray"])
    shutil.copy(first, bad["renamed"])
    bad["moved"].parent.mkdir(parents=True)
    shutil.copy(first, bad["moved"])
    bad["truncated"].parent.mkdir(parents=True, exist_ok=True)
    bad["truncated"].write_bytes(first.read_bytes()[: first.stat().st_size // 2])
    two = pq.read_table(first)
    two = pa.concat_tables([two, two])
    two = two.set_column(two.schema.get_field_index("cell_id"), "cell_id", pa.array([specs[4].cell_id] * 2))
    bad["two rows"].parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(two, bad["two rows"])
    return sweep, genuine, bad


def test_the_reader_counts_only_verified_cell_files(planted, capsys, monkeypatch):
    from asp_dist.errors import SchemaError
    from asp_dist.results import store

    sweep, genuine, bad = planted
    monkeypatch.setattr(store, "_WARNED", set())
    assert store.cell_files(sweep) == sorted(genuine)
    err = capsys.readouterr().err
    for path in bad.values():
        assert f"asp-dist: warning: {path} is not counted" in err
    assert "is not in a cells/domain=<domain>/method=<method>/ directory" in err
    assert f"not '{bad['renamed'].stem}' as its name says" in err
    assert "row in the directory of signaling/zzz" in err
    assert "cannot be read as Parquet" in err and "holds 2 rows" in err
    assert len(err.splitlines()) == len(bad)
    assert store.cell_files(sweep) == sorted(genuine) and capsys.readouterr().err == ""  # warned once
    assert store.done_cell_ids(sweep) == {p.stem for p in genuine}
    assert len(store.read_rows(sweep)) == 2
    with pytest.raises(SchemaError, match="is not counted|holds|is not in|cannot be read"):
        store.read_table(sweep, strict=True)
    with pytest.raises(SchemaError):
        store.cell_files(sweep, strict=True)
    with pytest.raises(SchemaError):
        open_inputs([sweep], strict=True)


def test_status_and_query_warn_about_planted_files_and_never_count_them(planted, capsys, monkeypatch):
    from asp_dist.results import store

    sweep, _, bad = planted
    monkeypatch.setattr(store, "_WARNED", set())
    assert main(["status", "exp", "--results", str(sweep.parent)]) == 0
    out, err = capsys.readouterr()
    assert out.splitlines()[-1].split() == ["total", "2", "0", "16"]
    assert sum("asp-dist: warning:" in line for line in err.splitlines()) == len(bad)
    monkeypatch.setattr(store, "_WARNED", set())
    assert main(["query", str(sweep), "--sql", "SELECT count(*) AS n FROM cells", "--format", "csv"]) == 0
    out, err = capsys.readouterr()
    assert out.split() == ["n", "2"] and str(bad["stray"]) in err
