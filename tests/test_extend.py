"""`asp-dist sweep SPACE --name NAME --extend`: a sweep grown to a grid that holds every stored cell keeps its
rows, failures and bases, trains only the new cells, and records the grid's history; anything else is one
line. On Ray: tests/test_sweep.py grows the finished smoke sweep with `--extend`, SIGKILLs the driver
mid-extension and resumes (every cell once, the stored rows untouched); tests/test_s3.py does the same on S3."""

from __future__ import annotations

import pytest
from harness import fingerprint, space

from asp_dist.cli import main
from asp_dist.errors import SweepError
from asp_dist.results import store
from asp_dist.sweep.ledger import extended_manifest, new_manifest
from asp_dist.sweep.packing import Packing
from asp_dist.sweep.spaces import expand, grid_hash

GRID = """
[[grid]]
fixed = {{ train_steps = {steps}, unpaired_size = 64 }}
axes = {{ domain = ["{domain}"], method = {methods}, paired = [2], trial = {trials} }}
"""


def grid(tmp_path, name="g.toml", steps=40, methods='["osp", "asp"]', trials="[0]", domain="signaling"):
    return space(tmp_path, GRID.format(steps=steps, methods=methods, trials=trials, domain=domain), name)


# ---- the rule, without Ray --------------------------------------------------------------------------------
def test_a_grid_that_adds_trials_grows_the_manifest_and_records_its_history(tmp_path):
    old = expand(grid(tmp_path, "a.toml"))
    new = expand(grid(tmp_path, "b.toml", trials="{ first = 0, last = 2 }"))
    stored = new_manifest("s", "a", old, Packing("trial", 21))
    grown = extended_manifest(stored, "b", new)
    assert grown["cells"] == [s.cell_id for s in new] and set(stored["cells"]) < set(grown["cells"])
    assert grown["grid_hash"] == grid_hash(new) and grown["space"] == "b" and grown["packing"] == stored["packing"]
    assert [(h["grid_hash"], h["cells"]) for h in grown["history"]] == [(stored["grid_hash"], 2), (grid_hash(new), 6)]
    again = extended_manifest(grown, "c", expand(grid(tmp_path, "c.toml", trials="{ first = 0, last = 3 }")))
    assert len(again["history"]) == 3 and again["created_at"] == stored["created_at"]


@pytest.mark.parametrize("change, says", [
    ({"trials": "[1]"}, "the new grid lacks 2 of its 2 cells"),  # a removed value
    ({"steps": 41}, "the new grid lacks 2 of its 2 cells"),  # a changed knob: other cell ids
])
def test_a_grid_that_drops_or_changes_a_stored_cell_is_refused(tmp_path, change, says):
    stored = new_manifest("s", "a", expand(grid(tmp_path, "a.toml")))
    with pytest.raises(SweepError, match=says):
        extended_manifest(stored, "b", expand(grid(tmp_path, "b.toml", **change)))


def test_new_cells_may_not_join_a_stored_pack(tmp_path):
    particles = expand(grid(tmp_path, "a.toml", domain="particles"))  # a domain whose cells sweeps pack
    stored = new_manifest("s", "a", particles, Packing("trial", 21))
    more_methods = expand(grid(tmp_path, "b.toml", methods='["pc", "osp", "asp"]', domain="particles"))
    with pytest.raises(SweepError, match="would change the Tune trial of pack particles/trial-0"):
        extended_manifest(stored, "b", more_methods)  # trial 0's pack would gain a member
    more_trials = expand(grid(tmp_path, "c.toml", trials="[0, 1]", domain="particles"))
    assert len(extended_manifest(stored, "c", more_trials)["cells"]) == 4  # a new trial: a new pack
    # One cell per trial: the new methods are fine.
    alone = new_manifest("s", "a", particles)
    assert len(extended_manifest(alone, "b", more_methods)["cells"]) == 3


def test_the_cli_refuses_before_anything_is_written(tmp_path, capsys):
    results = tmp_path / "results"
    results.mkdir()
    (results / "s").mkdir()
    store.write_manifest(results / "s", new_manifest("s", "a", expand(grid(tmp_path, "a.toml"))))
    before = fingerprint(results)
    bigger = grid(tmp_path, "b.toml", trials="[0, 1]")
    assert main(["sweep", bigger, "--name", "s", "--results", str(results)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("asp-dist: error: sweep 's'") and err.endswith("or --extend to add the new cells to this sweep")
    assert main(["sweep", grid(tmp_path, "c.toml", trials="[1]"), "--name", "s", "--results", str(results),
                 "--extend"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--extend keeps every cell of sweep 's'" in err[0]
    assert fingerprint(results) == before
