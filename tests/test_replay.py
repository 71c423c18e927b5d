"""`asp-dist replay SWEEP CELL_ID` (asp_dist/sweep/replay.py): a finished cell trained again from its stored
spec gives its stored row bit for bit on the same code and machine — a lone cell with the sweep's stored
base or a base trained again, a packed member with its whole pack — and a row that differs is reported
column by column with exit 1. Sweeps are built without Ray: rows written as the trial writes them."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest
from budgets import tiny_spec

from asp_dist.cli import main
from asp_dist.results import store
from asp_dist.sweep.base_cache import get_base
from asp_dist.sweep.ledger import new_manifest
from asp_dist.sweep.packing import Packing, make_units
from asp_dist.sweep.replay import replay_cell
from asp_dist.training.cell import run_cell
from asp_dist.training.engines import run_pack


def lone_sweep(tmp_path, stored_base: bool):
    specs = [tiny_spec("signaling", method=m, paired=2, trial=0).resolved() for m in ("pc", "asp")]
    sweep = tmp_path / "lone"
    store.write_manifest(sweep, new_manifest("lone", "test", specs))
    for spec in specs:
        base = get_base(spec, store.bases_dir(sweep))[0] if stored_base else None
        store.write_row(sweep, run_cell(spec, base=base), "lone")
    return sweep, specs


@pytest.mark.parametrize("stored_base", [True, False], ids=["stored-base", "base-trained-again"])
def test_a_lone_cell_replays_bit_for_bit(tmp_path, stored_base, capsys):
    sweep, specs = lone_sweep(tmp_path, stored_base)
    assert store.bases_dir(sweep).exists() == stored_base
    before = sorted(p.name for p in sweep.rglob("*"))
    result = replay_cell(sweep, specs[1].cell_id)
    assert result.identical and result.how == "alone" and result.compared > 50, result.text()
    assert sorted(p.name for p in sweep.rglob("*")) == before, "replay wrote into the sweep"
    assert main(["replay", str(sweep), specs[1].cell_id]) == 0
    assert "identical: all" in capsys.readouterr().out


def test_a_changed_row_is_reported_column_by_column_with_exit_1(tmp_path, capsys):
    sweep, specs = lone_sweep(tmp_path, stored_base=True)
    spec = specs[1]
    path = store.cell_path(sweep, spec.domain, spec.method, spec.cell_id)
    table = pq.read_table(path)
    planted = table.set_column(table.schema.get_field_index("eval_mixed"), "eval_mixed",
                               [[table.column("eval_mixed")[0].as_py() + 1e-9]])
    pq.write_table(planted, path)
    result = replay_cell(sweep, spec.cell_id)
    assert [c for c, _, _ in result.differs] == ["eval_mixed"]
    assert main(["replay", str(sweep), spec.cell_id]) == 1
    out = capsys.readouterr().out
    assert "1 of" in out and "| eval_mixed |" in out and "same code revision" in out


def test_a_row_made_on_another_kind_of_cpu_says_so(tmp_path, capsys):
    """Every row names the CPU (and torch's vector kernels) that trained it; replaying a row from another CPU
    names both, instead of calling the difference a reproducibility bug."""
    sweep, specs = lone_sweep(tmp_path, stored_base=True)
    spec = specs[1]
    path = store.cell_path(sweep, spec.domain, spec.method, spec.cell_id)
    table = pq.read_table(path)
    here = table.column("cpu_model")[0].as_py()
    assert here and here.endswith(")") and "(" in here  # "<model name> (<capability>)"
    moved = table.set_column(table.schema.get_field_index("cpu_model"), "cpu_model", [["Other CPU (AVX2)"]])
    moved = moved.set_column(moved.schema.get_field_index("eval_mixed"), "eval_mixed",
                             [[table.column("eval_mixed")[0].as_py() + 1e-9]])
    pq.write_table(moved, path)
    result = replay_cell(sweep, spec.cell_id)
    assert [c for c, _, _ in result.differs] == ["eval_mixed"]  # cpu_model is where, not what: never "differs"
    assert result.provenance == [("cpu_model", "Other CPU (AVX2)", here)]
    assert "other code, packages or CPU" in result.text() and "same code revision" not in result.text()


def test_a_packed_member_replays_with_its_pack(tmp_path):
    specs = [tiny_spec("levers", method=m, paired=p, trial=0).resolved() for m in ("pc", "osp", "asp") for p in (1, 3)]
    packing = Packing("trial", 21)
    (unit,) = make_units(specs, packing)
    assert unit.pack_id is not None
    sweep = tmp_path / "packed"
    store.write_manifest(sweep, new_manifest("packed", "test", specs, packing))
    bases = {s.base_key: get_base(s, store.bases_dir(sweep))[0] for s in unit.specs}
    for r in run_pack(list(unit.specs), bases=bases):
        store.write_row(sweep, dict(r.row, pack=unit.pack_id), "packed")
    member = unit.specs[2].cell_id
    result = replay_cell(sweep, member)
    assert result.identical and result.how == f"in its pack {unit.pack_id} (6 cells)", result.text()


def test_replay_refuses_what_it_cannot_replay_in_one_line(tmp_path, capsys):
    sweep, specs = lone_sweep(tmp_path, stored_base=True)
    assert main(["replay", str(sweep), "signaling-asp-p2-t0-nonexistent"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("asp-dist: error: no cell 'signaling-asp-p2-t0-nonexistent'") and err.count("\n") == 1
    assert main(["replay", str(tmp_path / "nowhere"), specs[0].cell_id]) == 2
    assert "is not a sweep" in capsys.readouterr().err
    store.cell_path(sweep, specs[0].domain, specs[0].method, specs[0].cell_id).unlink()
    assert main(["replay", str(sweep), specs[0].cell_id]) == 2
    assert "has no row" in capsys.readouterr().err


def test_a_refusal_right_after_reading_the_row_exits_2_not_134(tmp_path):
    """The refusal of an edited row comes a moment after pyarrow read it. Read through a Python file object, an
    Arrow pool thread still dropping that file took the GIL while the interpreter finalized and died in a C++
    destructor (std::terminate, exit 134 after the right line): 8 runs of 20 on 2026-12-06, none since the row is
    read by its path. The command's own process, as a user runs it, several times."""
    import os
    import subprocess
    import sys

    sweep, specs = lone_sweep(tmp_path, stored_base=True)
    spec = specs[1]
    path = store.cell_path(sweep, spec.domain, spec.method, spec.cell_id)
    table = pq.read_table(path)
    pq.write_table(table.set_column(table.schema.get_field_index("pack"), "pack", [["edited-pack"]]), path)
    for _ in range(4):
        proc = subprocess.run([sys.executable, "-m", "asp_dist", "replay", str(sweep), spec.cell_id],
                              capture_output=True, text=True, timeout=300, check=False, env=dict(os.environ))
        lines = proc.stderr.splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert lines[0].startswith("asp-dist: error: cell ") and "was trained in pack edited-pack" in lines[0]
