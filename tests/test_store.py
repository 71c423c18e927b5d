"""The result store: pinned schema, atomic one-file-per-cell writes, layout, manifest, failures, the
reader (and pandas / pyarrow / DuckDB reading the folder as-is), and the shared base cache."""

from __future__ import annotations

import multiprocessing as mp
import os
from pathlib import Path

import duckdb
import pandas as pd
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from asp_dist.core.registry import DOMAINS
from asp_dist.errors import SchemaError
from asp_dist.results import store
from asp_dist.spec import FIELD_NAMES, CellSpec
from asp_dist.sweep.base_cache import base_path, get_base
from asp_dist.training.cell import run_cell
from asp_dist.training.row import row_table
from asp_dist.training.row import schema as row_schema


@pytest.fixture(scope="module")
def rows():
    """Real rows of three signaling cells (two methods, two paired counts)."""
    out = []
    for method, paired in (("pc", 2), ("asp", 2), ("asp", 4)):
        spec = CellSpec(domain="signaling", method=method, paired=paired, train_steps=30, batch_size=16,
                        unpaired_size=64)
        out.append(dict(run_cell(spec), ray_node_id="node-a", ray_version="x"))
    return out


def test_schema_pins_spec_metric_and_cell_columns(rows):
    sch = row_schema()
    assert set(FIELD_NAMES) <= set(sch.names)
    for domain in DOMAINS.values():
        for metric in domain.metrics:
            assert sch.field(f"eval_{metric}").type == pa.float64()
    assert sch.field("paired").type == pa.int64()
    assert sch.field("lr").type == pa.float64()
    assert sch.field("record_figure_data").type == pa.bool_()
    assert pa.types.is_dictionary(sch.field("domain").type)
    for col in ("sweep_id", "ray_node_id", "code_revision", "node", "time_train_wall_s", "base_key"):
        assert col in sch.names
    # Every column run_cell writes is pinned: a new column in cell.py fails here first.
    assert set(rows[0]) <= set(sch.names)


def test_unknown_column_is_an_error_and_missing_is_null(rows):
    with pytest.raises(SchemaError, match="not_a_column"):
        row_table(dict(rows[0], not_a_column=1))
    partial = {k: v for k, v in rows[0].items() if k != "loss_disc"}
    table = row_table(partial)
    assert table.column("loss_disc").to_pylist() == [None]
    assert table.schema == row_schema(rows[0]["domain"])


def test_write_is_atomic_fixed_name_and_never_overwrites(tmp_path, rows):
    row = rows[0]
    assert store.write_row(tmp_path, row, sweep_id="s1")
    path = store.cell_path(tmp_path, row["domain"], row["method"], row["cell_id"])
    assert path.exists() and path.parent.name == f"method={row['method']}"
    before = path.read_bytes()
    assert not store.write_row(tmp_path, dict(row, eval_mixed=-1.0), sweep_id="s2")
    assert path.read_bytes() == before
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".")], "temp file left behind"
    assert store.done_cell_ids(tmp_path) == {row["cell_id"]}
    # A hidden temp file of a crashed writer is not a finished cell.
    (path.parent / ".other.123.tmp").write_bytes(b"partial")
    assert store.done_cell_ids(tmp_path) == {row["cell_id"]}


def test_dataset_reads_with_pandas_pyarrow_and_duckdb(tmp_path, rows):
    for row in rows:
        store.write_row(tmp_path, row, sweep_id="s1")
    (store.cells_dir(tmp_path) / "domain=signaling" / "method=asp" / ".crashed.tmp").write_bytes(b"junk")
    cells = store.cells_dir(tmp_path)
    by_pandas = pd.read_parquet(cells, filters=None)
    by_arrow = ds.dataset(cells, exclude_invalid_files=True).to_table().to_pandas()
    by_duckdb = duckdb.sql(f"select * from read_parquet('{cells}/**/*.parquet')").df()
    for df in (by_pandas, by_arrow, by_duckdb):
        assert len(df) == 3
        assert sorted(df["method"].astype(str)) == ["asp", "asp", "pc"]
        assert set(df["domain"].astype(str)) == {"signaling"}
        assert sorted(df["paired"]) == [2, 2, 4]
    grouped = duckdb.sql(f"select method, count(*) n from read_parquet('{cells}/**/*.parquet') "
                         f"group by method order by method").fetchall()
    assert grouped == [("asp", 2), ("pc", 1)]
    df = store.read_rows(tmp_path)
    assert list(df["cell_id"]) == sorted(r["cell_id"] for r in rows)
    assert df["domain"].tolist() == ["signaling"] * 3 and df["sweep_id"].tolist() == ["s1"] * 3
    original = {r["cell_id"]: r for r in rows}
    for rec in df.to_dict("records"):
        assert rec["eval_mixed"] == original[rec["cell_id"]]["eval_mixed"]


def test_read_rows_of_empty_sweep_has_the_schema(tmp_path):
    df = store.read_rows(tmp_path)
    assert len(df) == 0 and "eval_mixed" in df.columns


def test_failures_and_manifest_roundtrip(tmp_path):
    store.record_failure(tmp_path, "c1", "signaling", "asp", "boom")
    store.record_failure(tmp_path, "c1", "signaling", "asp", "boom again")
    info = store.failed_cells(tmp_path)["c1"]
    assert info["times_failed"] == 2 and info["error"] == "boom again"
    store.clear_failure(tmp_path, "c1")
    assert store.failed_cells(tmp_path) == {}
    assert store.read_manifest(tmp_path) is None
    store.write_manifest(tmp_path, {"grid_hash": "abc", "cells": ["c1"]})
    assert store.read_manifest(tmp_path)["grid_hash"] == "abc"
    (tmp_path / store.MANIFEST).write_text("{not json")
    with pytest.raises(SchemaError, match="not valid JSON"):
        store.read_manifest(tmp_path)
    (tmp_path / store.MANIFEST).write_text('{"cell_ids": ["c1"]}')  # not the store's shape
    with pytest.raises(SchemaError, match="list of cell ids under 'cells'"):
        store.read_manifest(tmp_path)


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", '{"times_failed": "many"}', "\udcff"])
def test_a_failure_record_that_is_not_one_still_marks_its_cell_failed_and_stops_no_reader(tmp_path, text):
    (tmp_path / store.FAILED_DIR).mkdir()
    (tmp_path / store.FAILED_DIR / "c1.json").write_text(text, errors="surrogateescape")
    record = store.failed_cells(tmp_path)["c1"]
    assert store.last_error_line(record)
    store.record_failure(tmp_path, "c1", "signaling", "pc", "boom")
    assert store.failed_cells(tmp_path)["c1"]["times_failed"] == 1


def test_layout_lookup_and_finished_files(tmp_path, rows):
    sweep = tmp_path / "results" / "exp"
    store.write_row(sweep, rows[0], sweep_id="exp")
    crashed = store.cell_path(sweep, "signaling", "asp", ".x.123.tmp").with_suffix(".parquet")
    crashed.parent.mkdir(parents=True)
    crashed.write_bytes(b"partial")
    (store.cells_dir(sweep) / "_staging").mkdir()
    (store.cells_dir(sweep) / "_staging" / "y.parquet").write_bytes(b"partial")
    assert store.cell_files(sweep) == [store.cell_path(sweep, "signaling", "pc", rows[0]["cell_id"])]
    assert store.is_sweep_dir(sweep) and not store.is_sweep_dir(tmp_path)
    assert store.locate_sweep("exp", results=tmp_path / "results") == sweep
    assert store.locate_sweep(str(sweep)) == sweep
    assert store.locate_sweep("ghost", results=tmp_path / "results") == Path("ghost")  # reported as missing


# ---- base cache ---------------------------------------------------------------------------------
def _ask_for_base(args):
    cache_dir, calls_file = args
    import asp_dist.sweep.base_cache as cache
    import asp_dist.training.bases as bases

    original = bases.train_accepted_base

    def counting(spec, progress=None):
        with open(calls_file, "a") as fh:
            fh.write("trained\n")
        import time
        time.sleep(0.5)  # widen the race window: the second process must wait, not train again
        return original(spec, progress)

    cache.train_accepted_base = counting
    spec = CellSpec(domain="signaling", method="asp", trial=3)
    base, cached = cache.get_base(spec, Path(cache_dir))
    return base.key, cached, base.score


def test_base_cache_trains_once_under_concurrent_requests(tmp_path):
    calls = tmp_path / "calls.txt"
    ctx = mp.get_context("spawn")
    with ctx.Pool(2) as pool:
        results = pool.map(_ask_for_base, [(str(tmp_path / "bases"), str(calls))] * 2)
    assert calls.read_text().count("trained") == 1
    assert sorted(r[1] for r in results) == [False, True]
    assert results[0][0] == results[1][0] == CellSpec(domain="signaling", trial=3).base_key
    spec = CellSpec(domain="signaling", method="pc", trial=3)  # another method shares the base
    base, cached = get_base(spec, tmp_path / "bases")
    assert cached and base.key == spec.resolved().base_key
    assert base_path(tmp_path / "bases", base.key).exists()
    assert not [p for p in (tmp_path / "bases").iterdir() if p.name.endswith(".tmp")]
    assert os.path.getsize(base_path(tmp_path / "bases", base.key)) > 0


def test_base_from_cache_gives_the_same_row_as_training_it(tmp_path):
    from asp_dist.training.row import comparable

    spec = CellSpec(domain="signaling", method="asp", paired=2, train_steps=30, batch_size=16, unpaired_size=64)
    get_base(spec, tmp_path)
    base, cached = get_base(spec, tmp_path)
    assert cached
    assert comparable(run_cell(spec, base=base)) == comparable(run_cell(spec))


def test_pinned_schema_file_roundtrip(tmp_path, rows):
    store.write_row(tmp_path, rows[1], sweep_id="s")
    path = store.cell_path(tmp_path, rows[1]["domain"], rows[1]["method"], rows[1]["cell_id"])
    assert pq.read_schema(path).remove_metadata() == row_schema(rows[1]["domain"])


def test_rejected_base_is_remembered_for_the_other_cells_of_its_trial(tmp_path, monkeypatch):
    import asp_dist.sweep.base_cache as cache
    from asp_dist.training.bases import BaseRejected

    calls = []
    original = cache.train_accepted_base
    monkeypatch.setattr(cache, "train_accepted_base", lambda spec, progress=None: calls.append(1) or original(spec))
    unreachable = dict(domain="particles", trial=2, base_train_steps=2, particles_base_envs=8, eval_episodes=8,
                       base_max_attempts=2, particles_accept_return=1e9)
    with pytest.raises(BaseRejected, match="no attempt of 2"):
        get_base(CellSpec(method="asp", **unreachable), tmp_path)
    assert cache.rejected_path(tmp_path, CellSpec(**unreachable).base_key).exists()
    with pytest.raises(BaseRejected, match="remembered in"):  # another cell of the trial: no retraining
        get_base(CellSpec(method="pc", paired=3, **unreachable), tmp_path)
    assert len(calls) == 1
    base, cached = get_base(CellSpec(**{**unreachable, "particles_accept_return": 0.0}), tmp_path)  # other key
    assert not cached and base.score >= 0.0 and len(calls) == 2


# ---- damaged cell files --------------------------------------------------------------------------------
def test_damaged_cell_files_are_found_and_set_aside_and_valid_ones_never_touched(rows, tmp_path):
    """What the sweep's driver does before it counts (tune._run): each kind of damage under a grid cell's own
    name is found and moved, with its curve, into damaged/<time>/; valid files, stray files and temp files are
    left alone. (End to end, with the cells trained again: tests/test_sweep.py, tests/test_s3.py.)"""
    extra = [dict(rows[0], cell_id=f"{rows[0]['cell_id']}-{i}") for i in range(4)]
    # rows that older code wrote (or anyone planted) without a finished evaluation: not done either
    extra += [dict(rows[0], cell_id=f"{rows[0]['cell_id']}-nan", eval_mixed=float("nan")),
              dict(rows[0], cell_id=f"{rows[0]['cell_id']}-null", eval_self_play_new=None)]
    grid = {r["cell_id"]: (r["domain"], r["method"]) for r in rows + extra}
    for row in rows + extra:
        store.write_curve(tmp_path, row, [{"step": 1.0}])
        assert store.write_row(tmp_path, row, "s")
    paths = {r["cell_id"]: store.cell_path(tmp_path, r["domain"], r["method"], r["cell_id"]) for r in rows + extra}
    cut, empty, wrong, dangling, nan, null = (paths[r["cell_id"]] for r in extra)
    cut.write_bytes(cut.read_bytes()[:100])
    empty.write_bytes(b"")
    wrong.write_bytes(paths[rows[1]["cell_id"]].read_bytes())
    dangling.unlink()
    dangling.symlink_to(tmp_path / "nowhere")
    stray = cut.with_name("not-in-the-grid.parquet")
    stray.write_bytes(b"junk")
    valid = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in paths.values()
             if p not in (cut, empty, wrong, dangling, nan, null)}

    found = store.damaged_cells(tmp_path, grid)
    assert set(found) == {r["cell_id"] for r in extra}
    assert "cannot be read as Parquet" in found[cut.stem][1] and "cannot be read as Parquet" in found[empty.stem][1]
    assert f"holds cell {rows[1]['cell_id']!r}" in found[wrong.stem][1]
    assert found[dangling.stem][1] == "is a symbolic link to nothing"
    assert found[nan.stem][1] == "has eval_mixed = nan; it is not a finished row"
    assert found[null.stem][1] == "has eval_self_play_new = None; it is not a finished row"
    assert not any(store.is_done(tmp_path, *grid[c], c) for c in found)
    assert set(store.read_rows(tmp_path)["cell_id"]) == {r["cell_id"] for r in rows}

    moved = store.set_aside_damaged(tmp_path, grid)
    assert sorted(old for old, _, _ in moved) == sorted([cut, empty, wrong, dangling, nan, null])
    for old, new, _ in moved:
        assert not os.path.lexists(old) and os.path.lexists(new)
        assert new.relative_to(tmp_path).parts[0] == store.DAMAGED_DIR
        curve = store.curve_path(tmp_path, *grid[old.stem], old.stem)
        assert not curve.exists(), "the curve of a cell that trains again stays with its damaged row"
    assert {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in valid} == valid and stray.exists()
    assert store.damaged_cells(tmp_path, grid) == {} and store.set_aside_damaged(tmp_path, grid) == []
    assert store.write_row(tmp_path, extra[3], "s"), "the dangling link's cell can be written again"


def test_verdict_index_spares_the_footers_of_known_files_and_never_hides_damage(rows, tmp_path, monkeypatch):
    """The sweep's driver keeps its good verdicts in cells/.verified.json, so the next process (`status`) does
    not parse the footers again; a file changed since (cut, rewritten, replaced) is verified afresh, a broken
    index is ignored, and a reader never writes the index."""
    for row in rows:
        assert store.write_row(tmp_path, row, "s")
    index = store.cells_dir(tmp_path) / store.VERDICTS_FILE
    paths = store.cell_files(tmp_path)
    assert len(paths) == 3 and not index.exists(), "a reader writes nothing"
    assert store.cell_files(tmp_path, remember=True) == paths and index.is_file()

    def fresh_process():  # what a new interpreter starts with
        monkeypatch.setattr(store, "_CHECKED", {})
        monkeypatch.setattr(store, "_INDEXED", {})

    fresh_process()
    opened = []
    real = store.parquet_metadata
    monkeypatch.setattr(store, "parquet_metadata", lambda p: opened.append(p) or real(p))
    assert store.cell_files(tmp_path) == paths and opened == [], "known files are not opened again"

    cut, replaced, kept = paths
    cut.write_bytes(cut.read_bytes()[:200])
    (tmp_path / "other.parquet").write_bytes(kept.read_bytes())
    os.replace(tmp_path / "other.parquet", replaced)  # another cell's row under this name: a new inode
    fresh_process()
    assert store.cell_files(tmp_path) == [kept]
    assert sorted(opened) == sorted([cut, replaced]), "only the changed files are verified again"

    (store.cells_dir(tmp_path) / store.VERDICTS_FILE).write_text('{"version": 1, "good": [1, 2]}')
    fresh_process()
    assert store.cell_files(tmp_path) == [kept]
