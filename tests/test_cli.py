import json
import subprocess
import sys

import pandas as pd
import pytest

from asp_dist.cli import main
from asp_dist.training.row import schema as row_schema


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
    import pyarrow.parquet as pq


    assert pq.read_schema(out).names == row_schema().names  # the sweep store's pinned schema
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
    assert main(["theory", "-S", "0", "-A", "2"]) == 2


def test_fields_lists_every_knob(capsys):
    assert main(["fields"]) == 0
    out = capsys.readouterr().out
    assert "lambda_unpaired" in out and "signaling_skew" in out
