"""The `asp-dist` command: cell, theory, fields, stats by sweep name, and its one-line user errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest
from test_stats import make_rows, write_sweep

from asp_dist.cli import main
from asp_dist.core.registry import DOMAINS
from asp_dist.training.row import schema as row_schema

EXAMPLES = Path(__file__).resolve().parents[1] / "results" / "examples"


def run(*args):
    return subprocess.run([sys.executable, "-m", "asp_dist.cli", *args], capture_output=True, text=True, timeout=120)


def test_cell_prints_row_and_writes_parquet(tmp_path, capsys):
    out = tmp_path / "row.parquet"
    rc = main(["cell", "--domain", "signaling", "--method", "asp", "--paired", "2", "--quiet",
               "--set", "train_steps=40", "--out", str(out)])
    assert rc == 0
    row = json.loads(capsys.readouterr().out)
    assert row["method"] == "asp" and row["train_steps"] == 40
    df = pd.read_parquet(out)
    assert len(df) == 1 and df.loc[0, "cell_id"] == row["cell_id"]
    assert pq.read_schema(out).names == row_schema("signaling").names  # the sweep store's pinned schema
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp file left


def test_existing_output_is_never_overwritten(tmp_path):
    out = tmp_path / "row.parquet"
    out.write_bytes(b"precious")
    r = run("cell", "--domain", "signaling", "--method", "pc", "--paired", "1", "--out", str(out))
    assert r.returncode == 2 and "never overwritten" in r.stderr
    assert out.read_bytes() == b"precious"


@pytest.mark.parametrize("args, message", [
    (["--domain", "mars", "--method", "asp", "--paired", "1"], "unknown domain 'mars'"),
    (["--domain", "signaling", "--method", "gail", "--paired", "1"], "unknown method 'gail'"),
    (["--domain", "signaling", "--method", "asp", "--paired", "1", "--set", "lr"], "--set expects KEY=VALUE"),
    (["--domain", "signaling", "--method", "asp", "--paired", "1", "--set", "foo=1"], "unknown cell field 'foo'"),
])
def test_bad_input_is_one_clear_line(args, message):
    r = run("cell", *args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and lines[0].startswith("asp-dist: error:")


def test_theory_command(capsys):
    assert main(["theory", "--states", "4", "--actions", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["log_adversarial_policies"] == pytest.approx(1.791759, abs=1e-5)  # ln 6
    with pytest.raises(SystemExit) as refused:  # a bound of the flag's type: argparse's exit 2
        main(["theory", "-S", "0", "-A", "2"])
    assert refused.value.code == 2


def test_fields_lists_every_knob_or_one_domain_s(capsys):
    assert main(["fields"]) == 0
    listed = {line.split()[0] for line in capsys.readouterr().out.splitlines()}
    assert "lambda_unpaired" in listed and "signaling_skew" in listed
    for domain in DOMAINS:
        assert main(["fields", "--domain", domain]) == 0
        shown = {line.split()[0] for line in capsys.readouterr().out.splitlines()}
        own = {f for f in listed if f.startswith(f"{domain}_")}
        others = {f for f in listed if f.startswith(tuple(f"{d}_" for d in DOMAINS if d != domain))}
        assert "lambda_unpaired" in shown and own <= shown and not shown & others
    assert main(["fields", "--domain", "particles"]) == 0  # a domain's own value of a common knob
    shown = dict(line.split()[:2] for line in capsys.readouterr().out.splitlines())
    assert (shown["lambda_unpaired_schedule"], shown["base_max_attempts"]) == ("warmup", "10")


def test_argparse_errors_are_one_line_too(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["cell", "--domain", "signaling"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(lines) == 1
    assert lines[0].startswith("asp-dist: error: the following arguments are required: --method, --paired")


def test_stats_of_a_sweep_named_under_results(tmp_path, monkeypatch):
    sweep = write_sweep(tmp_path / "res" / "sig", make_rows(trials=range(4)), manifest_ids=[])
    monkeypatch.chdir(tmp_path)  # ./sig does not exist: the name must be found under --results
    assert main(["stats", "sig", "--results", "res", "--no-figures", "--bootstrap", "100", "--quiet"]) == 0
    summary = pd.read_parquet(sweep / "stats" / "summary.parquet")
    assert set(summary["treatment"]) == {"pc", "osp", "asp"} and summary["n"].eq(4).all()
    assert "asp-dist stats sig --results res" in (sweep / "report.md").read_text()


def test_stats_of_a_merged_example_file(tmp_path, capsys):
    merged = str(EXAMPLES / "paper-levers.parquet")
    assert main(["stats", merged, "--out", str(tmp_path), "--no-figures", "--bootstrap", "100", "--quiet"]) == 0
    assert len(pd.read_parquet(tmp_path / "stats" / "summary.parquet")) > 0
    capsys.readouterr()
    assert main(["stats", merged, "--no-figures"]) == 2
    assert capsys.readouterr().err == ("asp-dist: error: several inputs or single files: "
                                       "say where to write the stats with --out DIR\n")
