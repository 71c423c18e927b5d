"""`asp-dist compare A B`: are two runs of a grid equivalent? (asp_dist/analysis/compare.py)"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from test_stats import make_rows, write_sweep

from asp_dist.analysis.compare import Margin, parse_margin, run_compare
from asp_dist.cli import main
from asp_dist.errors import SpecError

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "results" / "examples"


def rerun(rows: list[dict], shift: float = 0.0, jitter: float = 0.0, seed: int = 1) -> list[dict]:
    """The same cells run again: metric + shift + a little noise, new cell ids."""
    rng = np.random.default_rng(seed)
    return [dict(r, eval_mixed=r["eval_mixed"] + shift + jitter * rng.normal(), cell_id=r["cell_id"] + "-b",
                 sweep_id="b") for r in rows]


@pytest.fixture
def sweeps(tmp_path):
    rows = make_rows(trials=range(8))
    return rows, write_sweep(tmp_path / "a", rows)


def cli(argv: list[str], capsys) -> tuple[int, str, str]:
    code = main([str(a) for a in argv] + ["--bootstrap", "500"])
    out, err = capsys.readouterr()
    return code, out, err


def test_agreeing_runs_are_equivalent(sweeps, tmp_path, capsys):
    rows, a = sweeps
    b = write_sweep(tmp_path / "b", rerun(rows, jitter=0.01))
    code, out, _ = cli(["compare", a, b], capsys)
    assert code == 0
    last = out.strip().splitlines()[-1]
    assert last.startswith("verdict: equivalent") and "12 groups" in last
    assert "groups: 12; intervals overlap in 12" in out


def test_a_shifted_copy_is_not_equivalent(sweeps, tmp_path, capsys):
    rows, a = sweeps
    b = write_sweep(tmp_path / "b", rerun(rows, shift=2.0))
    code, out, _ = cli(["compare", a, b], capsys)
    assert code == 1
    assert out.strip().splitlines()[-1].startswith("verdict: NOT equivalent: 12 of 12 group(s) have a median outside")


def test_a_margin_decides_on_the_per_trial_difference(sweeps, tmp_path, capsys):
    rows, a = sweeps
    b = write_sweep(tmp_path / "b", rerun(rows, shift=0.01))  # medians agree, every trial 0.01 apart
    assert cli(["compare", a, b], capsys)[0] == 0
    code, out, _ = cli(["compare", a, b, "--margin", "0.005"], capsys)
    assert code == 1 and "beyond the margin ±0.005" in out
    code, out, _ = cli(["compare", a, b, "--margin", "0.02"], capsys)
    assert code == 0 and "within ±0.02" in out.strip().splitlines()[-1]


def test_groups_in_one_run_only_are_not_equivalent(sweeps, tmp_path, capsys):
    rows, a = sweeps
    b = write_sweep(tmp_path / "b", [r for r in rerun(rows) if r["paired"] != 4])
    code, out, _ = cli(["compare", a, b], capsys)
    assert code == 1 and "3 group(s) only in A and 0 only in B" in out


def test_bad_inputs_exit_2_with_one_line(sweeps, tmp_path, capsys):
    _, a = sweeps
    for argv in (["compare", a, tmp_path / "missing"], ["compare", a, a, "--margin", "abc"],
                 ["compare", a, a, "--by", "nope"], ["compare", a, a, "--domain", "vae"]):
        code, out, err = cli(argv, capsys)
        assert code == 2 and out == ""
        assert len(err.strip().splitlines()) == 1 and err.startswith("asp-dist: error: ")


def test_parse_margin():
    assert parse_margin("0.5") == Margin(0.5) and parse_margin("5%") == Margin(0.05, relative=True)
    assert parse_margin("5%").at(-200.0) == pytest.approx(10.0)
    with pytest.raises(SpecError):
        parse_margin("-1")


def test_reproduces_the_packed_vs_single_cell_verdict_in_docs_performance():
    """docs/performance.md records the VAE comparison's verdict line; the committed rows reproduce it."""
    text = (ROOT / "docs" / "performance.md").read_text()
    recorded = re.search(r"Verdict line: (groups: 42;[^\n]*)", text).group(1).strip()
    result = run_compare(str(EXAMPLES / "paper-packed-vae.parquet"), str(EXAMPLES / "paper-vae.parquet"),
                         domain="vae", by=["vae_latent_dim"], n_boot=5000, seed=0)
    lines = result.text().splitlines()
    assert lines[-2] == recorded and result.equivalent
