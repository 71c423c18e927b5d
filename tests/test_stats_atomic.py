"""A stats run that fails midway (a full disk, Ctrl-C) leaves its output directory exactly as it was: the job
writes into a stage and moves the files into place only once all are written (asp_dist.fsutil.staged_directory).
A full disk is one line and exit 2, like every other user-side failure."""

from __future__ import annotations

import errno
import os

import pytest
from harness import fingerprint
from test_stats import make_rows, write_sweep

from asp_dist.analysis import latex_tables
from asp_dist.cli import main
from asp_dist.fsutil import move_files_into, staged_directory


def fail_after_first_write(monkeypatch, error: BaseException) -> list:
    """The LaTeX tables' writer writes one file, then raises `error`: by then stats/*.parquet|md are written."""
    real, calls = latex_tables.write_atomic, []

    def write_then_fail(path, text):
        calls.append(path)
        if len(calls) > 1:
            raise error
        return real(path, text)

    monkeypatch.setattr(latex_tables, "write_atomic", write_then_fail)
    return calls


STATS = ["--quiet", "--no-figures", "--bootstrap", "100"]


@pytest.fixture
def sweep_with_stats(tmp_path):
    """A sweep whose directory already holds a stats run (the default --out): what a failed rerun must keep."""
    sweep = write_sweep(tmp_path / "sw", make_rows(trials=range(3)))
    assert main(["stats", str(sweep), *STATS, "--formats", "md,html"]) == 0
    (sweep / "stats" / "summary.md").write_text("an older run's table\n")  # to tell the runs apart
    return sweep


def test_a_full_disk_is_one_line_exit_2_and_the_old_stats_stay(sweep_with_stats, tmp_path, monkeypatch, capsys):
    before = fingerprint(tmp_path)
    calls = fail_after_first_write(monkeypatch, OSError(errno.ENOSPC, "No space left on device"))
    assert main(["stats", str(sweep_with_stats), *STATS]) == 2
    assert len(calls) == 2, "the failure was not midway"
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("asp-dist: error: no space left writing the stats to "), lines
    assert fingerprint(tmp_path) == before, "a failed run changed or left files"


def test_a_new_out_directory_is_not_left_behind(sweep_with_stats, tmp_path, monkeypatch, capsys):
    before = fingerprint(tmp_path)
    fail_after_first_write(monkeypatch, OSError(errno.ENOSPC, "No space left on device"))
    assert main(["stats", str(sweep_with_stats), *STATS, "--out", str(tmp_path / "new" / "deeper")]) == 2
    assert "no space left" in capsys.readouterr().err
    assert fingerprint(tmp_path) == before


def test_ctrl_c_midway_leaves_the_old_stats(sweep_with_stats, tmp_path, monkeypatch):
    before = fingerprint(tmp_path)
    fail_after_first_write(monkeypatch, KeyboardInterrupt())
    assert main(["stats", str(sweep_with_stats), *STATS]) == 130
    assert fingerprint(tmp_path) == before


def test_a_run_that_succeeds_replaces_the_old_files_and_leaves_no_stage(sweep_with_stats):
    assert main(["stats", str(sweep_with_stats), *STATS]) == 0
    assert (sweep_with_stats / "stats" / "summary.md").read_text() != "an older run's table\n"
    assert (sweep_with_stats / "stats" / "summary.tex").exists() and (sweep_with_stats / "report.html").exists()
    assert not [p for p in sweep_with_stats.rglob(".*")], "a stage or temp file was left"


def test_moving_into_place_is_all_or_nothing(tmp_path, monkeypatch):
    """A rename that fails after others succeeded puts the replaced files back and removes the new ones."""
    dest = tmp_path / "dest"
    (dest / "stats").mkdir(parents=True)
    (dest / "stats" / "a.md").write_text("old a")
    (dest / "keep.txt").write_text("mine")
    before = fingerprint(tmp_path)
    real, renames = os.replace, []

    def replace(src, dst):
        renames.append(dst)
        if len(renames) == 4:  # figures/f.svg and report.md in, the old stats/a.md aside, then the new one: full
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst)

    with pytest.raises(OSError), staged_directory(dest) as stage:
        assert stage.name == "dest"  # named as its destination: the report's title and links read the same
        for rel in ("stats/a.md", "stats/b.md", "figures/f.svg", "report.md"):
            (stage / rel).parent.mkdir(parents=True, exist_ok=True)
            (stage / rel).write_text("new")
        monkeypatch.setattr(os, "replace", replace)
    monkeypatch.undo()
    assert len(renames) == 4 + 1  # the failing rename, then the old a.md put back (the new files are removed)
    assert fingerprint(tmp_path) == before


def test_move_files_into_replaces_and_adds(tmp_path):
    src, dest = tmp_path / "src", tmp_path / "dest"
    (src / "stats").mkdir(parents=True)
    (src / "stats" / "a.md").write_text("new a")
    (src / "report.md").write_text("report")
    (dest / "stats").mkdir(parents=True)
    (dest / "stats" / "a.md").write_text("old a")
    move_files_into(src, dest, backup=tmp_path / "backup")
    assert (dest / "stats" / "a.md").read_text() == "new a" and (dest / "report.md").read_text() == "report"
    assert (tmp_path / "backup" / "stats" / "a.md").read_text() == "old a"  # the caller removes the backup
