"""`asp-dist query`: filters, columns, SQL over the view `cells`, output formats, inputs (sweep names
under --results, directories, loose and merged files), user errors."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout
from pathlib import Path

import pandas as pd
import pyarrow.dataset as ds
import pytest
from test_stats import make_rows, write_sweep

from asp_dist.cli import main
from asp_dist.errors import SpecError
from asp_dist.results.query import find_inputs, open_inputs, run_query, write_result

EXAMPLES = Path(__file__).resolve().parents[1] / "results" / "examples"


@pytest.fixture
def sweep(tmp_path):
    return write_sweep(tmp_path / "q", make_rows(trials=range(3), knobs={"signaling_skew": [0.0, 1.0]}),
                       manifest_ids=[])


def test_where_filter_and_columns(sweep):
    df = run_query([sweep], where="method = 'asp' AND paired >= 2 AND signaling_skew = 1",
                   columns=["method", "paired", "trial", "eval_mixed"])
    assert list(df.columns) == ["method", "paired", "trial", "eval_mixed"]
    assert len(df) == 2 * 3 and set(df["method"]) == {"asp"} and df["paired"].min() == 2
    assert list(df["paired"]) == sorted(df["paired"])  # ordered by the key columns


def test_sql_over_cells_view_agrees_with_pandas_and_pyarrow(sweep):
    sql = ("SELECT method, median(eval_mixed) AS median, count(*) AS n FROM cells "
           "WHERE paired BETWEEN 1 AND 4 GROUP BY method ORDER BY method")
    via_sql = run_query([sweep], sql=sql).set_index("method")
    inputs = open_inputs([sweep])
    # Files written without a pinned schema (all-null columns) need the unified schema and no hive parsing.
    rows = pd.read_parquet([str(f) for f in inputs.files], partitioning=None, schema=inputs.schema)
    via_pandas = rows[rows.paired.between(1, 4)].groupby("method")["eval_mixed"].agg(["median", "count"])
    table = inputs.dataset().to_table(filter=(ds.field("paired") >= 1) & (ds.field("paired") <= 4))
    via_arrow = table.to_pandas().groupby("method")["eval_mixed"].median()
    assert via_sql["n"].tolist() == via_pandas["count"].tolist() == [18, 18, 18]
    assert via_sql["median"].tolist() == pytest.approx(via_pandas["median"].tolist())
    assert via_sql["median"].tolist() == pytest.approx(via_arrow.tolist())


def test_manifest_and_stats_folders_are_not_rows(sweep):
    (sweep / "stats").mkdir()
    pd.DataFrame({"x": [1]}).to_parquet(sweep / "stats" / "summary.parquet")
    assert len(run_query([sweep])) == 3 * 4 * 3 * 2
    # A bare directory of cells works too, and so do single files.
    files = find_inputs([sweep]).files
    assert len(run_query([sweep / "cells"])) == len(files)
    assert len(run_query([files[0], files[1]])) == 2


def test_user_errors_are_one_line_spec_errors(sweep, tmp_path):
    with pytest.raises(SpecError, match="unknown column 'eval_mixd'; did you mean eval_mixed"):
        run_query([sweep], columns=["eval_mixd"])
    with pytest.raises(SpecError, match="--where"):
        run_query([sweep], where="methd = 'asp'")
    with pytest.raises(SpecError, match="SQL query failed"):
        run_query([sweep], sql="SELEC 1")
    with pytest.raises(SpecError, match="does not exist"):
        run_query([tmp_path / "nope"])
    with pytest.raises(SpecError, match="no finished cells"):
        (tmp_path / "empty").mkdir()
        run_query([tmp_path / "empty"])
    with pytest.raises(SpecError, match="needs --out"):
        write_result(pd.DataFrame({"a": [1]}), "parquet")
    with pytest.raises(SpecError, match="cannot write --out"):
        write_result(pd.DataFrame({"a": [1]}), "csv", tmp_path / "no-such-dir" / "x.csv")


def test_formats_through_the_cli(sweep, tmp_path):
    buf = io.StringIO()
    with redirect_stdout(buf):
        rc = main(["query", str(sweep), "--where", "paired = 0 AND trial = 0", "--columns", "method,eval_mixed",
                   "--format", "json"])
    lines = [json.loads(line) for line in buf.getvalue().splitlines()]
    assert rc == 0 and len(lines) == 6 and set(lines[0]) == {"method", "eval_mixed"}
    out = tmp_path / "x.parquet"
    assert main(["query", str(sweep), "--sql", "SELECT * FROM cells WHERE method = 'pc'", "--format", "parquet",
                 "--out", str(out)]) == 0
    assert len(pd.read_parquet(out)) == 24
    csv = tmp_path / "x.csv"
    assert main(["query", str(sweep), "--columns", "cell_id", "--format", "csv", "--out", str(csv),
                 "--limit", "5"]) == 0
    assert csv.read_text().splitlines()[0] == "cell_id" and len(csv.read_text().splitlines()) == 6
    assert main(["query", str(sweep), "--columns", "nope"]) == 2


def test_a_sweep_name_is_looked_up_under_results(sweep, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path.parent)  # neither ./q nor ./results/q exists here
    assert main(["query", "q", "--results", str(tmp_path), "--sql", "SELECT count(*) AS n FROM cells",
                 "--format", "csv"]) == 0
    assert capsys.readouterr().out.split() == ["n", str(3 * 4 * 3 * 2)]
    assert main(["query", "q", "--sql", "SELECT 1"]) == 2  # default --results is ./results
    err = capsys.readouterr().err.strip()
    assert err.startswith("asp-dist: error: q does not exist") and "--results results" in err and "\n" not in err


def test_merged_example_datasets_are_read_as_they_are():
    path = EXAMPLES / "paper-levers.parquet"
    df = run_query([path], sql="SELECT method, count(*) AS n FROM cells GROUP BY method ORDER BY method")
    assert df["method"].tolist() == ["asp", "osp", "pc"] and df["n"].sum() == 420
    assert len(run_query([path], where="paired = 4 AND trial = 0", columns=["method", "eval_mixed"])) == 3
