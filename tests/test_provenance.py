"""What a sweep ran with (asp_dist/sweep/provenance.py): env/<n>/ per run, never overwritten, the git state of
the source (with its diff when dirty), and the report's Provenance section with its warnings. The sweeps'
own records are checked end to end in tests/test_sweep.py (local, with Ray's node) and tests/test_s3.py."""

from __future__ import annotations

import json
import subprocess

import pandas as pd

from asp_dist.analysis.document import Table, Text
from asp_dist.analysis.report import provenance_blocks
from asp_dist.sweep import provenance


def test_each_run_gets_its_own_numbered_record(tmp_path):
    first = provenance.record(tmp_path, space_text="[[grid]]\n", grid="g", argv=["asp-dist", "sweep", "my space"])
    second = provenance.record(tmp_path, space_text=None, grid="space s, 3 cells, grid hash abc")
    assert (first.name, second.name) == ("1", "2")
    assert (first / "command.txt").read_text() == "asp-dist sweep 'my space'\n"
    assert (first / "space.toml").read_text() == "[[grid]]\n"
    assert "resumed from the manifest: space s, 3 cells, grid hash abc" in (second / "space.toml").read_text()
    machine = json.loads((first / "machine.json").read_text())
    assert machine["cores"] >= 1 and machine["cpu_model"] and "OMP_NUM_THREADS" in machine["threads"]
    assert machine["started_at"].endswith("+00:00")
    names = [line.split("==")[0].lower() for line in (first / "distributions.txt").read_text().split()]
    assert names == sorted(names) and {"asp-dist", "torch", "ray"} <= set(names)


def test_a_dirty_source_tree_is_recorded_with_its_diff(tmp_path, monkeypatch):
    src = tmp_path / "src"
    (src / "asp_dist").mkdir(parents=True)
    (src / "asp_dist" / "x.py").write_text("A = 1\n")
    git = ["git", "-C", str(src), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(git[:3] + ["init", "-q"], check=True)
    subprocess.run(git + ["add", "."], check=True)
    subprocess.run(git + ["commit", "-qm", "x"], check=True)
    monkeypatch.setattr(provenance, "SOURCE", src)
    clean = provenance.record(tmp_path / "sweep", space_text="", grid="g", argv=["a"])
    assert "dirty false" in (clean / "git.txt").read_text() and not (clean / "git.diff").exists()
    (src / "asp_dist" / "x.py").write_text("A = 2\n")
    dirty = provenance.record(tmp_path / "sweep", space_text="", grid="g", argv=["a"])
    assert "dirty true" in (dirty / "git.txt").read_text()
    assert "+A = 2" in (dirty / "git.diff").read_text()
    monkeypatch.setattr(provenance, "SOURCE", tmp_path / "not-a-checkout")
    unknown = provenance.record(tmp_path / "sweep", space_text="", grid="g", argv=["a"])
    assert (unknown / "git.txt").read_text().startswith("revision unknown")


def _rows(revisions: list[str], torch_versions: list[str]) -> pd.DataFrame:
    return pd.DataFrame({"sweep_id": "s", "code_revision": revisions, "torch_version": torch_versions,
                         "asp_dist_version": "0.1"})


def test_the_report_warns_when_a_sweep_mixes_code_or_has_dirty_rows():
    calm = provenance_blocks(_rows(["abc", "abc"], ["2.13", "2.13"]))
    assert isinstance(calm[2], Table) and "none from a dirty tree" in calm[-1].md
    table = calm[2].df
    assert table.loc[table["column"] == "code_revision", "values"].item() == "abc (2)"
    mixed = provenance_blocks(_rows(["abc", "def+dirty"], ["2.13", "2.12"]))
    warning = mixed[-1]
    assert isinstance(warning, Text) and warning.md.count("**warning**") == 3
    assert "mixes 2 values of code_revision" in warning.md and "1 row(s) from a dirty tree" in warning.md
    assert provenance_blocks(pd.DataFrame({"eval_mixed": [1.0]})) == []


def test_the_report_warns_when_a_sweep_ran_on_two_kinds_of_cpu():
    rows = _rows(["abc"] * 3, ["2.13"] * 3).assign(cpu_model=["AMD EPYC (AVX512)", "Intel Xeon (AVX512)", None])
    blocks = provenance_blocks(rows)
    table = blocks[2].df
    values = table.loc[table["column"] == "cpu_model", "values"].item()
    assert values == "AMD EPYC (AVX512) (1), Intel Xeon (AVX512) (1), unknown (1)"
    assert blocks[-1].md.count("**warning**") == 1 and "ran on 2 kinds of CPU" in blocks[-1].md
    # Rows older than the column (null, "unknown") are not a second kind.
    same = provenance_blocks(_rows(["abc"] * 2, ["2.13"] * 2).assign(cpu_model=["Intel Xeon (AVX512)", None]))
    assert "at most one known kind of CPU" in same[-1].md
