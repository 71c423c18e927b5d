"""Packed sweeps (`asp-dist sweep SPACE --pack trial|method`, asp_dist/sweep/packing.py and
sweep/trial.py): cells grouped into packs deterministically from the grid, one Tune trial per pack,
rows one Parquet file per cell with the pinned schema (and a `pack` column), resume per cell.

Fast tests (no Ray): the packs as a function of the grid; the flags and the packing kept in the
manifest; bad flags are one line, exit 2, nothing written; rows written before the `pack` column
existed still read; the pack trainable outside Ray (tune.report faked, as test_sweep_lifecycle does)
gives run_pack's rows, records a member whose base is rejected as that member's failure, continues a
pack from its checkpoint and writes only the members without a row; the same on S3 (moto); every
domain with a packed trainer keeps the registry's contract and runs and restores a tiny pack.

Slow tests (Ray, CLI subprocesses, each on its own Ray temp dir): a mixed particle + signaling space
swept with --pack trial and without; a packed sweep whose driver is SIGKILLed while a pack is
mid-run, then resumed.
"""

from __future__ import annotations

import inspect
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import ray
from budgets import TINY, tiny_spec
from harness import (
    checkpointed_running_trials,
    clean,
    cli,
    env,
    expected_rows,
    finished_row,
    kill_group,
    newest_state,
    s3_env,
    start_moto,
    stop_now,
)
from packed_cases import DOMAINS as PACKED_DOMAINS
from packed_cases import trainer_class

from asp_dist.cli import main
from asp_dist.errors import SweepError
from asp_dist.results import store
from asp_dist.results.query import run_query
from asp_dist.spec import CellSpec
from asp_dist.sweep import ledger
from asp_dist.sweep.base_cache import get_base, rejected_path
from asp_dist.sweep.packing import (
    DEFAULT_PACK_SIZE,
    Packing,
    Unit,
    bases_first,
    make_units,
    resolve_packing,
    spread_bases,
)
from asp_dist.sweep.spaces import expand
from asp_dist.training.engines import pack_key, run_pack, supports
from asp_dist.training.row import comparable
from asp_dist.training.row import schema as row_schema

# Differ between two runs of one spec beyond row.VOLATILE_COLUMNS: where and by which sweep it ran, the
# working tree's revision, and how it was trained.
PLACE_COLUMNS = {"sweep_id", "ray_node_id", "ray_version", "code_revision", "pack"}
TINY_PARTICLES = "\n".join(f"{k} = {v!r}" for k, v in TINY["particles"].items())
TINY_SIGNALING = ", ".join(f"{k} = {v!r}" for k, v in TINY["signaling"].items())


def write_space(tmp_path: Path, *, train_steps: int | None = None, paired=(0, 2), signaling: bool = True,
                name="grid.toml") -> str:
    """Tiny particle cells (3 methods x `paired` x trials {0, 1}) and, optionally, 2 tiny signaling cells."""
    text = f"[fixed]\n{TINY_PARTICLES}\n"
    if train_steps is not None:
        text = text.replace(f"train_steps = {TINY['particles']['train_steps']}", f"train_steps = {train_steps}")
    text += ('\n[[grid]]\naxes = { domain = ["particles"], method = ["pc", "osp", "asp"], '
             f'paired = {list(paired)}, trial = [0, 1] }}\n')
    if signaling:
        text += (f'\n[[grid]]\nfixed = {{ {TINY_SIGNALING} }}\n'
                 'axes = { domain = ["signaling"], method = ["pc", "asp"], paired = [2], trial = [0] }\n')
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def stable(row: dict) -> dict:
    """A row without what differs between runs of one spec in one packing (time, place, resumption)."""
    return {k: clean(v) for k, v in comparable(row).items() if k not in PLACE_COLUMNS}


def assert_rows(rows, expected: dict[str, dict]) -> None:
    """Stored rows (a DataFrame) are `expected` (run_pack's rows, by cell id): every column of those equal,
    every other column of the pinned schema (other domains' metrics) null."""
    got = {r["cell_id"]: stable(r) for r in rows.to_dict("records")}
    assert sorted(got) == sorted(expected)
    for cid, row in got.items():
        assert {k: v for k, v in row.items() if k in expected[cid]} == expected[cid], cid
        assert all(v is None for k, v in row.items() if k not in expected[cid]), cid


def direct_rows(units: list[Unit], bases_dir) -> dict[str, dict]:
    """run_pack over each pack (and nothing else), with the sweep's stored bases: what a packed sweep must write."""
    out = {}
    for unit in units:
        if unit.pack_id is None:
            continue
        bases = {s.base_key: get_base(s, bases_dir)[0] for s in unit.specs}
        for result in run_pack(list(unit.specs), bases=bases, curves=True):
            assert result.error is None, result.error
            out[result.spec.cell_id] = stable(result.row)
    return out


# ---- packs from the grid -----------------------------------------------------------------------------------
def test_packs_are_a_deterministic_function_of_the_grid(tmp_path):
    specs = expand(write_space(tmp_path))
    unpackable = CellSpec(domain="particles", method="asp", paired=2, trial=0, particles_replay_size=100,
                          **TINY["particles"]).resolved()
    specs = specs + [unpackable]
    particle_ids = {s.cell_id for s in specs if s.domain == "particles"} - {unpackable.cell_id}

    by_trial = make_units(specs, Packing("trial", DEFAULT_PACK_SIZE))
    packs = [u for u in by_trial if u.pack_id]
    assert [len(u.specs) for u in packs] == [6, 6]
    assert {u.pack_id.rsplit("/", 2)[0] for u in packs} == {"particles/trial-0", "particles/trial-1"}
    assert all(u.pack_id.endswith("/1of1-k6") for u in packs)
    for u in packs:
        assert len({s.trial for s in u.specs}) == 1 and [s.cell_id for s in u.specs] == sorted(u.cell_ids)
        assert "/" not in u.name and u.name.startswith("pack_")
    singles = {u.specs[0].cell_id for u in by_trial if u.pack_id is None}
    assert singles == {s.cell_id for s in specs if s.domain == "signaling"} | {unpackable.cell_id}
    assert sorted(c for u in by_trial for c in u.cell_ids) == sorted(s.cell_id for s in specs)  # each cell once

    # The same packs whatever the order of the cells (resume rebuilds them from the manifest), and a
    # cap splits a group into near-equal packs, its cells sorted by cell id.
    assert {u.pack_id: u.cell_ids for u in make_units(list(reversed(specs)), Packing("trial", 21)) if u.pack_id} \
        == {u.pack_id: u.cell_ids for u in packs}
    capped = [u for u in make_units(specs, Packing("trial", 4)) if u.pack_id]
    assert sorted(len(u.specs) for u in capped) == [3, 3, 3, 3]
    trial0 = sorted(s.cell_id for s in specs if s.cell_id in particle_ids and s.trial == 0)
    assert [u.cell_ids for u in capped if "trial-0" in u.pack_id] == [trial0[:3], trial0[3:]]

    by_method = [u for u in make_units(specs, Packing("method", 3)) if u.pack_id]
    assert sorted(len(u.specs) for u in by_method) == [2] * 6  # 4 cells per method -> 2 packs of 2
    assert all(len({s.method for s in u.specs}) == 1 for u in by_method)
    assert [u.pack_id for u in make_units(specs, Packing("method", 3)) if u.pack_id] == [u.pack_id for u in by_method]
    # A group of one packable cell runs alone, as does every cell with --pack cell.
    assert all(u.pack_id is None for u in make_units(specs[:1] + specs[-4:], Packing("trial", 21)))
    assert all(u.pack_id is None for u in make_units(specs, Packing()))


def test_units_are_spread_over_bases_so_concurrent_workers_do_not_wait_on_one_base(tmp_path):
    """A sweep hands its workers the first unit of every base, then the second of each, ...: the same units in
    another order, in which neighbours need distinct bases wherever the grid has more than one left."""
    specs = expand(write_space(tmp_path))
    for packing in (Packing(), Packing("trial", 4)):
        units = make_units(specs, packing)
        spread = spread_bases(units)
        assert sorted(u.name for u in spread) == sorted(u.name for u in units)
        bases = [u.specs[0].base_key for u in spread]
        rounds = [bases[:len(set(bases))]]  # the first round: every base once, in the grid's order
        assert rounds[0] == list(dict.fromkeys(u.specs[0].base_key for u in units))
        left = {b: bases.count(b) for b in set(bases)}
        for a, b in zip(bases, bases[1:]):  # adjacent units share a base only once every other base is used up
            left[a] -= 1
            assert a != b or sum(n > 0 for k, n in left.items() if k != a) == 0
    assert spread_bases(units) == spread_bases(list(units))  # a function of the units alone


def test_a_packed_sweeps_missing_bases_come_first_as_units_of_their_own(tmp_path):
    """bases_first: one base-only unit per base the units need that the cache has not settled, in the order the
    units first need them, before every unit; such a unit runs no cell and is named by its base."""
    specs = [s for s in expand(write_space(tmp_path)) if s.domain == "particles"]
    units = spread_bases(make_units(specs, Packing("method", 21)))  # each pack spans both trials' bases
    keys = list(dict.fromkeys(s.base_key for u in units for s in u.specs))
    assert len(keys) == 2
    ordered = bases_first(units, lambda key: False)
    assert [u.base_only for u in ordered] == [True, True] + [False] * len(units) and ordered[2:] == units
    assert [u.specs[0].base_key for u in ordered[:2]] == keys
    assert all(u.cell_ids == [] and u.name == f"base_{u.specs[0].base_key}" for u in ordered[:2])
    assert bases_first(units, lambda key: key == keys[0])[:1] == ordered[1:2]  # a settled base is not trained again
    assert bases_first(units, lambda key: True) == units


def test_a_base_only_unit_stores_its_base_and_records_no_cell(trainable, tmp_path):
    sweep_tune, fake = trainable
    spec = next(s for s in expand(write_space(tmp_path, signaling=False)) if s.trial == 0)
    sweep_dir = tmp_path / "exp"
    unit = Unit((spec,), base_only=True)
    sweep_tune.train_cell({"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 30.0)})
    assert store.base_path(store.bases_dir(sweep_dir), spec.base_key).exists()
    assert fake.reports[-1] == {"cell_done": 0, "base_done": 1, "skipped": 0}
    sweep_tune.train_cell({"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 30.0)})  # stored meanwhile
    assert fake.reports[-1] == {"cell_done": 0, "base_done": 1, "skipped": 1}
    other = next(s for s in expand(write_space(tmp_path, signaling=False)) if s.trial == 1)
    rejected_path(store.bases_dir(sweep_dir), other.base_key).write_text('{"error": "planted by the test"}')
    sweep_tune.train_cell({"cell": sweep_tune.unit_config(Unit((other,), base_only=True), sweep_dir, "exp", 30.0)})
    assert fake.reports[-1] == {"cell_done": 0, "base_done": 0}
    assert not cell_files(sweep_dir) and not store.failed_cells(sweep_dir)  # its cells fail when they run


def test_a_packed_trainer_kept_out_of_sweeps_leaves_its_cells_single(monkeypatch):
    """The VAE's packed trainer is slower than its single-cell path on CPU (in_sweeps = False): --pack
    leaves VAE cells single, so the packs of existing sweeps do not change with its registration."""
    specs = [tiny_spec("vae", method=m, paired=2, trial=t).resolved() for m in ("pc", "osp", "asp") for t in (0, 1)]
    assert all(supports(s) for s in specs)
    for mode in ("trial", "method"):
        assert all(u.pack_id is None for u in make_units(specs, Packing(mode, 21)))
    monkeypatch.setattr(trainer_class("vae"), "in_sweeps", True)
    assert [len(u.specs) for u in make_units(specs, Packing("trial", 21))] == [3, 3]


def test_packing_is_fixed_when_a_sweep_starts(tmp_path):
    specs = expand(write_space(tmp_path))
    assert resolve_packing(None, None, None) == Packing()
    assert resolve_packing("trial", None, None) == Packing("trial", DEFAULT_PACK_SIZE)
    assert resolve_packing("method", 5, None) == Packing("method", 5)
    started = ledger.new_manifest("exp", "grid", specs, Packing("trial", 7))
    assert started["packing"] == {"mode": "trial", "size": 7}
    assert resolve_packing(None, None, started) == Packing("trial", 7)  # resume keeps it
    assert resolve_packing("trial", None, started) == Packing("trial", 7)
    assert resolve_packing("trial", 7, started) == Packing("trial", 7)
    for mode, size in (("cell", None), ("method", None), ("trial", 8), (None, 8)):
        with pytest.raises(SweepError, match="was started with --pack trial --pack-size 7"):
            resolve_packing(mode, size, started)
    old = {k: v for k, v in ledger.new_manifest("exp", "grid", specs).items() if k != "packing"}
    assert resolve_packing(None, None, old) == Packing()  # a sweep started before packs existed
    with pytest.raises(SweepError, match="was started with one cell per trial"):
        resolve_packing("trial", None, old)


def run_cli(capsys, *argv):
    try:
        code = main(list(argv))
    except SystemExit as e:  # argparse's own errors
        code = e.code
    return code, capsys.readouterr().err


def one_line_error(code, err, needle):
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("asp-dist: error: "), err
    assert needle in lines[0], lines[0]


def test_bad_pack_flags_are_one_line_exit_2_and_nothing_written(capsys, tmp_path):
    grid = write_space(tmp_path)
    results = tmp_path / "results"
    for flags, needle in ((["--pack", "nonsense"], "--pack 'nonsense': choose one of cell, trial, method"),
                          (["--pack", "trial", "--pack-size", "0"], "--pack-size must be >= 1, got 0"),
                          (["--pack-size", "0"], "--pack-size must be >= 1, got 0"),
                          (["--pack", "cell", "--pack-size", "4"], "--pack-size needs --pack trial"),
                          (["--pack", "trial", "--pack-size", "two"], "argument --pack-size: invalid int value")):
        one_line_error(*run_cli(capsys, "sweep", grid, "--results", str(results), *flags), needle)
        one_line_error(*run_cli(capsys, "resume", "exp", "--results", str(results), *flags), needle)
    one_line_error(*run_cli(capsys, "sweep", grid, "--results", str(results), "--pack-size", "4"),
                   "--pack-size needs --pack trial or --pack method")
    assert not results.exists()

    # A sweep started with one packing refuses another, for sweep and resume alike, touching nothing.
    sweep_dir = results / "exp"
    sweep_dir.mkdir(parents=True)
    store.write_manifest(sweep_dir, ledger.new_manifest("exp", "grid", expand(grid), Packing("trial", 21)))
    before = {p: p.read_bytes() for p in sweep_dir.rglob("*") if p.is_file()}
    one_line_error(*run_cli(capsys, "sweep", grid, "--name", "exp", "--results", str(results), "--pack", "method"),
                   "was started with --pack trial --pack-size 21, not --pack method --pack-size 21")
    one_line_error(*run_cli(capsys, "resume", "exp", "--results", str(results), "--pack", "cell"),
                   "was started with --pack trial --pack-size 21, not one cell per trial")
    one_line_error(*run_cli(capsys, "resume", "exp", "--results", str(results), "--pack-size", "3"),
                   "not --pack trial --pack-size 3")
    assert {p: p.read_bytes() for p in sweep_dir.rglob("*") if p.is_file()} == before


def test_rows_without_the_pack_column_still_read(tmp_path):
    """Files written before the `pack` column existed read beside new ones: null there, strict reader included."""
    spec = CellSpec(domain="signaling", method="asp", paired=2, **TINY["signaling"]).resolved()
    other = spec.replace(method="pc").resolved()
    new_row = finished_row(spec, pack="signaling/trial-0/x/1of1-k2")
    assert store.write_row(tmp_path, new_row, sweep_id="exp")
    old = pa.Table.from_pylist([finished_row(other, eval_mixed=0.25, sweep_id="old")],
                               schema=pa.schema([f for f in row_schema("signaling") if f.name != "pack"]))
    path = store.cell_path(tmp_path, other.domain, other.method, other.cell_id)
    path.parent.mkdir(parents=True)
    pq.write_table(old, path)
    assert "pack" not in pq.read_schema(path).names
    for strict in (False, True):
        df = store.read_rows(tmp_path, strict=strict).set_index("cell_id")
        assert df.loc[spec.cell_id, "pack"] == "signaling/trial-0/x/1of1-k2"
        assert clean(df.loc[other.cell_id, "pack"]) is None
    got = run_query([str(tmp_path)], sql="SELECT method, pack FROM cells ORDER BY method")
    assert got["method"].tolist() == ["asp", "pc"]
    assert [clean(v) for v in got["pack"]] == ["signaling/trial-0/x/1of1-k2", None]


# ---- the pack trainable outside Ray ---------------------------------------------------------------------------
class FakeTune:
    """tune.report / tune.get_checkpoint of one trial: reports recorded, checkpoints copied aside."""

    def __init__(self, keep: Path):
        self.keep, self.reports, self.saved, self.restore_from = keep, [], [], None

    def report(self, metrics, checkpoint=None):
        if checkpoint is not None:
            copy = self.keep / f"ckpt-{len(self.saved)}"
            shutil.copytree(checkpoint.path, copy)
            self.saved.append(copy)
        self.reports.append(metrics)

    def get_checkpoint(self):
        from ray.tune import Checkpoint

        return None if self.restore_from is None else Checkpoint.from_directory(str(self.restore_from))


@pytest.fixture
def trainable(monkeypatch, tmp_path):
    from asp_dist.sweep import trial
    from asp_dist.sweep import tune as sweep_tune

    fake = FakeTune(tmp_path / "kept")
    fake.keep.mkdir()

    class RuntimeContext:
        def get_node_id(self):
            return "node-0"

    monkeypatch.setattr(sweep_tune.tune, "report", fake.report)
    monkeypatch.setattr(sweep_tune.tune, "get_checkpoint", fake.get_checkpoint)
    monkeypatch.setattr(trial.ray, "get_runtime_context", RuntimeContext)
    system_tmp = tmp_path / "system-tmp"
    system_tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(system_tmp))
    monkeypatch.chdir(tmp_path)  # on S3 checkpoints are staged in the trial's working directory
    return sweep_tune, fake


def cell_files(sweep_dir) -> dict[str, object]:
    return {p.stem: p for p in store.cell_files(sweep_dir, strict=True)}


def test_pack_trainable_writes_run_packs_rows_resumes_from_its_checkpoint_and_writes_each_cell_once(
        trainable, tmp_path):
    sweep_tune, fake = trainable
    specs = [s for s in expand(write_space(tmp_path, signaling=False)) if s.trial == 0]  # 40 updates
    (unit,) = make_units(specs, Packing("trial", 21))
    sweep_dir = tmp_path / "exp"
    config = {"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 1e-9)}  # a checkpoint after every update

    sweep_tune.train_cell(config)
    assert not ray.is_initialized(), "train_cell outside Ray started a local Ray to look for a tracker hub"
    files = cell_files(sweep_dir)
    assert sorted(files) == sorted(unit.cell_ids) and not store.failed_cells(sweep_dir)
    rows = store.read_rows(sweep_dir).set_index("cell_id")
    assert (rows["pack"] == unit.pack_id).all() and (rows["ray_node_id"] == "node-0").all()
    assert rows["resumed_from_step"].isna().all()
    assert len(store.read_curves(sweep_dir).groupby("cell_id")) == 6
    expected = direct_rows([unit], store.bases_dir(sweep_dir))
    assert_rows(store.read_rows(sweep_dir), expected)  # bit for bit: the same pack, trained directly
    assert len(fake.saved) == 39
    # The last result, as Tune's readers show it: counts, the cell ids, each member's final eval_* metrics.
    last = fake.reports[-1]
    assert {k: last[k] for k in ("cell_done", "cells_written", "cell_failed")} == \
        {"cell_done": 1, "cells_written": 6, "cell_failed": 0}
    assert last["cell_ids"] == ",".join(unit.cell_ids) and last["pack_id"] == unit.pack_id
    assert {cid: m["eval_mixed"] for cid, m in last["members"].items()} == rows["eval_mixed"].to_dict()
    staging = sweep_dir / sweep_tune.TUNE_DIR / sweep_tune.CKPT_TMP
    assert not any(staging.iterdir()), "a staged checkpoint was left behind"

    # A crash after two members were written: the pack restarts from its checkpoint at update 20, trains
    # as a whole, and writes only the four missing members - the rows of an uninterrupted run.
    kept = set(unit.cell_ids[:2])
    mtimes = {cid: files[cid].stat().st_mtime_ns for cid in kept}
    for cid, spec in zip(unit.cell_ids, unit.specs):
        if cid not in kept:
            files[cid].unlink()
            store.curve_path(sweep_dir, spec.domain, spec.method, cid).unlink()
    fake.restore_from, fake.reports = fake.saved[19], []
    sweep_tune.train_cell(config)
    files = cell_files(sweep_dir)
    assert sorted(files) == sorted(unit.cell_ids)
    assert {cid: files[cid].stat().st_mtime_ns for cid in kept} == mtimes  # never rewritten
    again = store.read_rows(sweep_dir).set_index("cell_id", drop=False)
    assert set(again.loc[sorted(set(unit.cell_ids) - kept), "resumed_from_step"]) == {20}
    assert_rows(again, expected)
    assert fake.reports[-1]["cells_written"] == 4

    # Every member done: the trial does nothing.
    fake.reports = []
    sweep_tune.train_cell(config)
    assert fake.reports == [{"cell_done": 1, "skipped": 1}]


def test_a_trial_whose_checkpoint_is_gone_starts_over_instead_of_failing(trainable, tmp_path, capfd):
    """Tune's experiment state may name a checkpoint already deleted (a newer one replaced it while the state
    was on its way to S3): the trial trains from the start, with a warning, and writes the rows of an
    uninterrupted run -- not a failure, not a trial lost."""
    sweep_tune, fake = trainable
    specs = [s for s in expand(write_space(tmp_path, paired=(2,), signaling=False)) if s.trial == 0]  # 3 cells
    (unit,) = make_units(specs, Packing("trial", 21))
    sweep_dir = tmp_path / "exp"
    gone = tmp_path / "checkpoint_000003"
    gone.mkdir()  # what Tune downloads for a checkpoint whose objects were deleted: an empty directory
    fake.restore_from = gone
    sweep_tune.train_cell({"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 1e9)})
    assert "checkpoint_000003 Tune restores this trial from holds no state" in capfd.readouterr().err
    assert not store.failed_cells(sweep_dir) and fake.reports[-1]["cells_written"] == 3
    rows = store.read_rows(sweep_dir)
    assert rows["resumed_from_step"].isna().all()
    assert_rows(rows, direct_rows([unit], store.bases_dir(sweep_dir)))


def test_each_members_trackers_have_its_end_before_its_row_is_written(trainable, tmp_path, monkeypatch):
    """A cell with a row is never trained again, so nothing would resend its last points or its end: the trial
    hands both to the tracker hub, and has the hub's answer, before writing the row (a driver killed between
    the two leaves a cell that trains again, never a tracker run short of its tail)."""
    from asp_dist.sweep import trial
    from asp_dist.tracking.hub import Feed

    sweep_tune, _ = trainable
    specs = [s for s in expand(write_space(tmp_path, paired=(2,), signaling=False)) if s.trial == 0]  # 3 cells
    (unit,) = make_units(specs, Packing("trial", 21))
    sweep_dir = tmp_path / "exp"
    seen = []

    class Hub:  # an actor handle's shape
        class points:
            remote = staticmethod(lambda batch: None)

        class finish:
            @staticmethod
            def remote(cell_id, final, step, error):
                seen.append((cell_id, bool(final), error, cell_id in cell_files(sweep_dir)))
                return cell_id

    def answered(ref, seconds):
        seen.append(("answered", ref, ref in cell_files(sweep_dir)))
        return True

    monkeypatch.setattr(trial, "_feed", lambda sweep, cells: Feed(Hub(), only=cells, wait=answered))
    sweep_tune.train_cell({"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 1e9)})
    assert sorted(cell_files(sweep_dir)) == sorted(unit.cell_ids)
    assert seen == [x for cid in unit.cell_ids for x in ((cid, True, None, False), ("answered", cid, False))]


@pytest.mark.parametrize("domain", PACKED_DOMAINS)
def test_every_registered_packed_trainer_runs_a_pack_and_restores_it_in_the_trainable(domain, trainable, tmp_path,
                                                                                       monkeypatch):
    """The registry's contract, for every domain with a packed trainer: its capabilities as attributes
    (asp_dist.training.engines); a tiny pack of the domain (one cell per method) trained by the sweep's
    trainable gives run_pack's rows, and continued from a mid-run checkpoint gives them again
    (also for a trainer kept out of sweeps by in_sweeps = False: its packs must work when asked for)."""
    trainer = trainer_class(domain)
    monkeypatch.setattr(trainer, "in_sweeps", True)
    assert trainer.packs and isinstance(trainer.lone, bool) and trainer.engine == trainer.__name__
    assert all(callable(getattr(trainer, name, None)) for name in ("supports", "pack_key", "build", "member_order"))
    params = inspect.signature(trainer.build).parameters
    assert list(params) == ["specs", "paired", "unpaired", "agents"]
    sweep_tune, fake = trainable
    specs = [tiny_spec(domain, method=m, paired=2, trial=0).resolved() for m in ("pc", "osp", "asp")]
    assert all(supports(s) for s in specs) and len({pack_key(s) for s in specs}) == 1
    (unit,) = make_units(specs, Packing("trial", 21))
    assert unit.pack_id is not None and len(unit.specs) == 3
    sweep_dir = tmp_path / "exp"
    config = {"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 1e-9)}  # a checkpoint after every update

    sweep_tune.train_cell(config)
    steps = specs[0].train_steps
    assert len(fake.saved) == steps - 1 and fake.reports[-1]["cells_written"] == 3
    expected = direct_rows([unit], store.bases_dir(sweep_dir))
    assert_rows(store.read_rows(sweep_dir), expected)

    for spec in unit.specs[1:]:  # two members lost: continue from the checkpoint after update steps // 2
        store.cell_path(sweep_dir, spec.domain, spec.method, spec.cell_id).unlink()
        store.curve_path(sweep_dir, spec.domain, spec.method, spec.cell_id).unlink()
    fake.restore_from, fake.reports = fake.saved[steps // 2 - 1], []
    sweep_tune.train_cell(config)
    rows = store.read_rows(sweep_dir).set_index("cell_id", drop=False)
    assert set(rows.loc[unit.cell_ids[1:], "resumed_from_step"]) == {steps // 2}
    assert_rows(rows, expected)
    assert fake.reports[-1]["cells_written"] == 2


def test_a_rejected_base_fails_its_members_only(trainable, tmp_path):
    sweep_tune, fake = trainable
    specs = [s for s in expand(write_space(tmp_path, signaling=False)) if s.method == "asp"]
    (unit,) = make_units(specs, Packing("method", 21))  # both trials' ASP cells in one pack
    sweep_dir = tmp_path / "exp"
    trial1 = next(s for s in specs if s.trial == 1)
    rejected = rejected_path(store.bases_dir(sweep_dir), trial1.base_key)
    rejected.parent.mkdir(parents=True)
    rejected.write_text('{"error": "no base met the bar (planted by the test)"}')

    sweep_tune.train_cell({"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 30.0)})
    done, failed = set(cell_files(sweep_dir)), store.failed_cells(sweep_dir)
    assert done == {s.cell_id for s in specs if s.trial == 0}
    assert set(failed) == {s.cell_id for s in specs if s.trial == 1}
    assert all("BaseRejected: no base met the bar (planted" in r["error"] for r in failed.values())
    last = fake.reports[-1]
    assert {k: last[k] for k in ("cell_done", "cells_written", "cell_failed")} == \
        {"cell_done": 0, "cells_written": 2, "cell_failed": 2}
    assert sorted(last["members"]) == sorted(done)  # final metrics of the written members only


def test_progress_and_failures_count_cells_not_packs(tmp_path):
    """The live view shows every member of a running pack as a running cell; a pack whose worker kept
    dying fails each of its members that has no row, as a single cell would."""
    import io
    from types import SimpleNamespace

    from asp_dist.sweep import tune as sweep_tune
    from asp_dist.sweep.progress import SweepCounter

    specs = expand(write_space(tmp_path))
    units = make_units(specs, Packing("trial", 21))
    sweep_dir = tmp_path / "exp"
    pack, single = next(u for u in units if u.pack_id), next(u for u in units if u.pack_id is None)
    done_member = pack.specs[0]
    store.write_row(sweep_dir, finished_row(done_member), "exp")
    grid = {s.cell_id: f"{s.domain}/{s.method}" for s in specs}
    counter = SweepCounter("exp", grid, {done_member.cell_id}, stream=io.StringIO())
    callback = sweep_tune.SweepCallback(str(sweep_dir), "exp", grid, counter)
    trials = [SimpleNamespace(config={"cell": sweep_tune.unit_config(u, sweep_dir, "exp", 30.0)}, status="RUNNING",
                              error_file=None, num_failures=3) for u in (pack, single)]
    callback.on_step_end(0, trials)
    assert counter.running == set(pack.cell_ids[1:]) | set(single.cell_ids) and counter.pending == len(specs) - 7
    assert [sweep_tune.trial_name(t) for t in trials] == [pack.name, single.cell_ids[0]]
    callback.on_trial_error(0, trials, trials[0])
    failed = store.failed_cells(sweep_dir)
    assert set(failed) == set(pack.cell_ids[1:])
    assert all(f"failed after 3 attempt(s) (in pack {pack.pack_id})" in r["error"] for r in failed.values())
    assert counter.failed == set(pack.cell_ids[1:])


@pytest.fixture(scope="module")
def s3_server(tmp_path_factory):
    pytest.importorskip("boto3")
    pytest.importorskip("moto")
    import test_s3

    proc, endpoint = start_moto(tmp_path_factory.mktemp("moto") / "moto.log")
    try:
        test_s3.s3_client(endpoint).create_bucket(Bucket=test_s3.BUCKET)
        yield test_s3, s3_env(AWS_ENDPOINT_URL=endpoint, AWS_ACCESS_KEY_ID="asp-test",
                              AWS_SECRET_ACCESS_KEY="asp-test-secret")
    finally:
        stop_now(proc)


def test_pack_trainable_on_s3(trainable, tmp_path, s3_server, monkeypatch):
    """The same trial with the sweep in a bucket: rows, curves and the shared bases through the store."""
    from asp_dist.results import location
    from asp_dist.results import s3 as results_s3

    test_s3, env = s3_server
    test_s3.use_env(monkeypatch, env)
    sweep_tune, fake = trainable
    specs = [s for s in expand(write_space(tmp_path, signaling=False)) if s.trial == 0 and s.paired == 2]
    (unit,) = make_units(specs, Packing("trial", 21))
    sweep_dir = location.as_path(f"s3://{test_s3.BUCKET}/packed/exp")
    try:
        sweep_tune.train_cell({"cell": sweep_tune.unit_config(unit, sweep_dir, "exp", 0.05)})
        rows = store.read_rows(sweep_dir)
        assert sorted(rows["cell_id"]) == sorted(unit.cell_ids) and (rows["pack"] == unit.pack_id).all()
        assert len(store.curve_files(sweep_dir)) == 3
        assert_rows(rows, direct_rows([unit], store.bases_dir(sweep_dir)))
        assert not (tmp_path / "exp").exists()
    finally:
        results_s3._CLIENTS.clear()
        results_s3._BUCKETS_CHECKED.clear()


# ---- sweeps on Ray -------------------------------------------------------------------------------------------
@pytest.fixture
def ray_temp():
    path = f"/tmp/asp-pk-{os.getpid()}"
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.mark.slow
def test_packed_and_single_cell_sweeps_of_a_mixed_space(tmp_path, ray_temp):
    """A packed sweep of a mixed space: particle cells in packs, signaling cells alone; each cell one file of the
    pinned schema, packed members bit for bit run_pack's and within rounding of the same cells run alone
    (run_cell: what a single-cell sweep writes, tests/test_sweep.py), each member its own tracker run, and
    status and query see cells, not packs."""
    grid = write_space(tmp_path, paired=(2,))  # 2 packs of 3 particle cells, 2 signaling cells alone
    specs = expand(grid)
    results = tmp_path / "results"
    packed = cli("sweep", grid, "--name", "packed", "--results", str(results), "--pack", "trial",
                 "--ray-temp-dir", ray_temp, "--logger", "json")
    assert packed.returncode == 0, packed.stderr[-3000:]
    assert "8/8 cells done, 0 failed" in packed.stdout
    # the bases first: two particle trials' and the signaling one's
    assert ("packed (--pack trial --pack-size 21: 2 pack(s) of 3 cells + 2 single cell(s); 3 base(s) missing: "
            "trained first)") in packed.stderr
    assert len(list((results / "packed" / "tune" / "run-1").glob("base_*"))) == 3

    files = store.cell_files(results / "packed", strict=True)  # one file per cell, the pinned schema
    assert sorted(p.stem for p in files) == sorted(s.cell_id for s in specs)
    assert all(pq.read_schema(p).remove_metadata() == row_schema(p.parts[-3][len("domain="):]) for p in files)
    units = make_units(specs, Packing("trial", 21))
    pack_of = {cid: u.pack_id for u in units for cid in u.cell_ids}
    rows = store.read_rows(results / "packed").set_index("cell_id", drop=False)
    assert {cid: clean(v) for cid, v in rows["pack"].items()} == pack_of  # null for the signaling cells: alone

    # Packed members: bit for bit what run_pack gives for the same packs; within rounding of single cells.
    expected = direct_rows(units, store.bases_dir(results / "packed"))
    assert_rows(rows[rows["pack"].notna()], expected)
    alone = expected_rows(specs)  # run_cell's rows
    for spec in specs:
        got, one = stable(rows.loc[spec.cell_id].to_dict()), alone[spec.cell_id]
        assert all(v is None for k, v in got.items() if k not in one), spec.cell_id  # other domains' columns
        got = {k: v for k, v in got.items() if k in one}
        if pack_of[spec.cell_id] is None:
            assert got == one, spec.cell_id
            continue
        for col in (c for c in got if c.startswith("eval_") and got[c] is not None):
            assert got[col] == pytest.approx(one[col], rel=1e-4, abs=1e-6), (spec.cell_id, col)
    curves = store.read_curves(results / "packed")
    assert len(curves.groupby("cell_id")) == 8
    # One tracker run per cell, packed members too: each its own curve, live, and its own final metrics.
    from asp_dist.tracking.cells import describe_cells

    for cell_id, cell in describe_cells(specs, "packed", "?").items():
        lines = [json.loads(x) for x in (results / "packed" / "trackers" / "json" /
                                         f"{cell.run_path}.jsonl").read_text().splitlines()]
        assert lines[0]["cell"]["cell_id"] == cell_id
        assert [x["step"] for x in lines[1:-1]] == [int(s) for s in curves.loc[curves["cell_id"] == cell_id, "step"]]
        assert lines[-1]["final"]["eval_mixed"] == rows.loc[cell_id, "eval_mixed"]

    # status and query count cells, not packs.
    status = cli("status", "packed", "--results", str(results)).stdout.splitlines()
    assert status[-1].split() == ["total", "8", "0", "0"]
    assert [line.split()[:2] for line in status[2:-1]] == [["particles", "asp"], ["particles", "osp"],
                                                             ["particles", "pc"], ["signaling", "asp"],
                                                             ["signaling", "pc"]], status
    counts = run_query([str(results / "packed")], sql="SELECT domain, method, count(*) AS n FROM cells GROUP BY ALL "
                                                      "ORDER BY ALL")
    assert counts.values.tolist() == [["particles", "asp", 2], ["particles", "osp", 2], ["particles", "pc", 2],
                                      ["signaling", "asp", 1], ["signaling", "pc", 1]]


@pytest.mark.slow
def test_a_killed_packed_sweep_resumes_each_pack_from_its_checkpoint_and_writes_each_cell_once(tmp_path, ray_temp):
    grid = write_space(tmp_path, train_steps=1500, signaling=False)
    specs = expand(grid)
    units = make_units(specs, Packing("trial", 21))
    second = units[1]
    results = tmp_path / "results"
    sweep_dir = results / "k"
    err_file = tmp_path / "err.txt"
    with open(err_file, "w") as err_fh:
        driver = subprocess.Popen([sys.executable, "-m", "asp_dist.cli", "sweep", grid, "--name", "k", "--results",
                                   str(results), "--pack", "trial", "--workers", "1", "--checkpoint-every", "0.3",
                                   "--ray-temp-dir", ray_temp], env=env(), start_new_session=True,
                                  stdout=subprocess.DEVNULL, stderr=err_fh)
    try:
        # One worker: the first pack finishes, then the second runs; kill the driver once Tune's experiment state
        # holds the second pack running with its second checkpoint (the first pack is complete by then).
        deadline = time.monotonic() + 240

        def second_checkpoint_in_the_state() -> bool:
            return checkpointed_running_trials(newest_state(sweep_dir / "tune" / "run-1")).get(second.name, -1) >= 1 \
                and not store.is_done(sweep_dir, "particles", second.specs[0].method, second.specs[0].cell_id)

        while driver.poll() is None and time.monotonic() < deadline and not second_checkpoint_in_the_state():
            time.sleep(0.05)
        assert driver.poll() is None, "the sweep ended before it could be interrupted: " + err_file.read_text()[-2000:]
        driver.send_signal(signal.SIGKILL)
        driver.wait(30)
    finally:
        kill_group(driver)
    before = {p.stem: p.stat().st_mtime_ns for p in store.cell_files(sweep_dir)}
    assert set(before) <= set(units[0].cell_ids) | set(second.cell_ids) and not set(before) & set(second.cell_ids)

    resumed = cli("resume", "k", "--results", str(results), "--ray-temp-dir", ray_temp)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"({len(before)} already done), packed (--pack trial --pack-size 21" in resumed.stderr
    files = store.cell_files(sweep_dir, strict=True)
    assert sorted(p.stem for p in files) == sorted(s.cell_id for s in specs)  # each cell exactly once
    assert {p.stem: p.stat().st_mtime_ns for p in files if p.stem in before} == before  # none rewritten
    rows = store.read_rows(sweep_dir).set_index("cell_id", drop=False)
    assert (rows.loc[second.cell_ids, "resumed_from_step"] > 0).all(), "the pack started over"
    assert (rows["pack"] == rows["cell_id"].map({c: u.pack_id for u in units for c in u.cell_ids})).all()
    # The resumed pack's rows are an uninterrupted run's (the first pack's ran uninterrupted).
    assert_rows(rows.loc[second.cell_ids], direct_rows([second], store.bases_dir(sweep_dir)))
    assert not store.failed_cells(sweep_dir)
