"""`asp-dist tune` (asp_dist.sweep.tune_plan, asp_dist.sweep.tuning): the plan's checks, the ranges' declarations,
per-method settings in spaces, the searcher's determinism, and a real run killed and resumed."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
import tomllib

import pandas as pd
import pytest
from harness import cli, kill_group, parquet_files, read_log, space, start_cli, wait_for, wait_until_gone

from asp_dist.errors import SweepError
from asp_dist.knobs import Knob, Range, choice, log_uniform
from asp_dist.spec import SEARCH
from asp_dist.sweep.spaces import expand
from asp_dist.sweep.tune_plan import TunePlan

GRID = """
[[grid]]
fixed = { train_steps = 150, unpaired_size = 256 }
[grid.axes]
domain = ["signaling"]
method = ["pc", "osp", "asp"]
paired = [2, 8]
trial = { first = 100, last = 101 }
"""


def plan_of(tmp_path, tune_table: str, grid: str = GRID) -> TunePlan:
    return TunePlan.from_space(space(tmp_path, grid + "\n[tune]\n" + tune_table))


# ---- the plan ------------------------------------------------------------------------------------------
def test_every_method_gets_the_same_budget_and_the_knobs_that_matter_to_it(tmp_path):
    plan = plan_of(tmp_path, "budget = 5\nseed = 3\n")
    assert plan.settings.budget == 5 and plan.settings.seed == 3 and plan.settings.search == "tpe"
    assert list(plan.searches) == ["pc", "osp", "asp"]
    assert all(len(s.cells) == 4 and {c.method for c in s.cells} == {s.method} for s in plan.searches.values())
    # PC trains on the paired loss alone: its learning rate only; OSP adds λ0; ASP the adversary's knobs too
    assert set(plan.searches["pc"].ranges) == {"lr"}
    assert set(plan.searches["osp"].ranges) == {"lr", "lambda_paired"}
    assert {"lr", "lambda_paired", "lambda_unpaired", "disc_lr", "disc_steps", "adversary_loss"} <= set(
        plan.searches["asp"].ranges)
    assert plan.objective_column == "eval_mixed" and plan.higher_is_better
    configured = plan.searches["osp"].configuration({"lr": 0.004, "lambda_paired": 2.0})
    assert [c.lr for c in configured] == [0.004] * 4 and len({c.cell_id for c in configured}) == 4


def test_a_space_narrows_widens_or_adds_ranges_and_names_a_methods_knobs(tmp_path):
    plan = plan_of(tmp_path, """
[tune.ranges]
lr = { log_uniform = [3e-4, 3e-3] }
batch_size = { int = [32, 256] }
[tune.knobs]
pc = ["lr", "batch_size"]
""")
    assert plan.searches["pc"].ranges == {"lr": log_uniform(3e-4, 3e-3), "batch_size": Range("int", 32, 256)}
    assert plan.searches["asp"].ranges["lr"] == log_uniform(3e-4, 3e-3)


@pytest.mark.parametrize("table,message", [
    ("budget = 0", "budget is the number of configurations per method"),
    ("search = 'grid'", "search must be one of tpe, random"),
    ("metric = 'accuracy'", "metric 'accuracy' is not one of signaling's"),
    ("[tune.ranges]\nlearning_rate = { log_uniform = [1e-4, 1e-2] }", "names 'learning_rate', which is no knob"),
    ("[tune.ranges]\nlr = { log_uniform = [1e-2, 1e-4] }", "an empty range"),
    ("[tune.ranges]\nlr = { log_uniform = [0, 1e-2] }", "must be above 0"),
    ("[tune.ranges]\nadversary_loss = { choice = [] }", "an empty choice"),
    ("[tune.ranges]\nlambda_schedule_frac = { uniform = [0.5, 1.5] }", "reaches 1.5, which a cell refuses"),
    ("[tune.ranges]\nadversary_loss = { choice = ['neg_bce', 'hinge'] }", "reaches 'hinge', which a cell refuses"),
    ("[tune.ranges]\nbase_train_steps = { int = [10, 20] }", "base_train_steps cannot be tuned"),
    ("[tune.ranges]\nsignaling_states = { int = [8, 16] }", "signaling_states cannot be tuned"),
    ("[tune.ranges]\nlr = [1e-4, 1e-2]", "write a range as one of"),
    ("[tune.knobs]\npc = []", "method pc has nothing to tune"),
    ("[tune.knobs]\npc = ['disc_width']", "names disc_width, which has no range"),
    ("[tune.knobs]\nvae = ['lr']", "names method(s) vae that its grid does not have"),
    ("budgets = 3", "unknown key(s) budgets in [tune]"),
    ("from_defaults = 1", "from_defaults must be true or false"),
])
def test_bad_tune_tables_are_refused_in_one_line(tmp_path, table, message):
    with pytest.raises(SweepError, match=re.escape(message)):
        plan_of(tmp_path, table)


def test_tuning_happens_on_calibration_trials_only(tmp_path):
    with pytest.raises(SweepError, match=r"tune on calibration trials \(100-999\); its grid has trial\(s\) 1000, 1001"):
        plan_of(tmp_path, "budget = 2", GRID.replace("first = 100, last = 101", "first = 1000, last = 1001"))
    with pytest.raises(SweepError, match="a tune run searches one domain's methods"):
        plan_of(tmp_path, "budget = 2", GRID.replace('domain = ["signaling"]', 'domain = ["signaling", "levers"]'))
    with pytest.raises(SweepError, match="it has no \\[tune\\] table"):
        TunePlan.from_space(space(tmp_path, GRID))


def test_the_cli_refuses_a_bad_tune_space_in_one_line_and_writes_nothing(tmp_path):
    bad = space(tmp_path, GRID + "\n[tune]\nbudget = 0\n")
    out = cli("tune", bad, "--results", str(tmp_path / "runs"), timeout=60)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and out.stderr.startswith("asp-dist: error: ")
    assert "budget" in out.stderr and not (tmp_path / "runs").exists()
    good = space(tmp_path, GRID + "\n[tune]\nbudget = 2\n", "good.toml")
    out = cli("tune", good, "--results", str(tmp_path / "runs"), "--budget", "0", timeout=60)
    assert out.returncode == 2 and "--budget" in out.stderr and not (tmp_path / "runs").exists()


# ---- ranges declared where the knobs are ------------------------------------------------------------------
def test_declared_ranges_are_valid_and_never_on_a_knob_that_shapes_the_base():
    from asp_dist.spec import BASE_COMMON, field_type

    assert SEARCH, "the common knobs declare ranges"
    for name, rng in SEARCH.items():
        assert rng.problems(name, field_type(name)) == [], name
        assert name not in BASE_COMMON
    shaping = Knob("mine_width", int, 8, "a width", search=choice(4, 8))
    assert any("shapes the base" in p for p in shaping.problems("mine"))
    assert Knob("mine_width", int, 8, "a width", shapes_base=False, search=choice(4, 8)).problems("mine") == []
    assert any("choices" in p for p in Knob("mine_w", int, 8, "w", shapes_base=False,
                                            search=choice("a", "b")).problems("mine"))


def test_fields_shows_the_ranges():
    out = cli("fields", timeout=60)
    assert out.returncode == 0
    line = next(x for x in out.stdout.splitlines() if x.startswith("disc_lr "))
    assert "[tune: log-uniform [0.0001, 0.01] (methods with adversarial)]" in line


# ---- per-method settings in a space: where tuned.toml goes ------------------------------------------------
def test_a_space_takes_per_method_settings_from_itself_and_from_settings_files(tmp_path):
    (tmp_path / "tuned.toml").write_text('[methods.asp]\nlr = 0.002\nlambda_unpaired = 0.3\n[methods.pc]\nlr = 0.005\n')
    path = space(tmp_path, 'settings = ["tuned.toml"]\n' + GRID + '\n[methods.asp]\nlambda_unpaired = 0.5\n')
    cells = expand(path)
    by_method = {m: [c for c in cells if c.method == m] for m in ("pc", "osp", "asp")}
    assert {c.lr for c in by_method["pc"]} == {0.005}
    assert {(c.lr, c.lambda_unpaired) for c in by_method["asp"]} == {(0.002, 0.5)}  # the space's own wins
    assert {c.lr for c in by_method["osp"]} == {expand(space(tmp_path, GRID, "plain.toml"))[0].lr}
    clash = space(tmp_path, GRID.replace("paired = [2, 8]", "paired = [2, 8]\nlr = [0.1]")
                  + "\n[methods.pc]\nlr = 0.005\n", "clash.toml")
    with pytest.raises(SweepError, match="lr is a grid axis and set for method pc"):
        expand(clash)
    with pytest.raises(SweepError, match="its settings file missing.toml does not exist"):
        expand(space(tmp_path, 'settings = ["missing.toml"]\n' + GRID, "missing-settings.toml"))


# ---- the searcher -------------------------------------------------------------------------------------------
def test_the_tpe_searcher_suggests_the_same_configurations_for_the_same_seed_and_results():
    """Batches of `workers` suggestions, told together: the same seed and the same objectives give the same
    configurations, whatever order the results come back in."""
    from asp_dist.sweep.tuning import _searcher, search_space

    plan = TunePlan.build("t", "t", expand("tune-smoke"), {
        "budget": 6, "seed": 7, "ranges": {"lr": {"log_uniform": [1e-3, 1e-1]}, "disc_steps": {"int": [1, 2]}},
        "knobs": {"asp": ["lr", "lambda_unpaired", "disc_steps", "adversary_loss"]}}, "t")
    ranges = plan.searches["asp"].ranges

    def suggestions(order):
        searcher, mode = _searcher(plan, 2, workers=2, search=plan.searches["asp"])
        searcher.set_search_properties("objective", mode, search_space(ranges))
        seen = []
        for batch in range(3):
            ids = [f"t{batch}{k}" for k in range(2)]
            configs = [searcher.suggest(i) for i in ids]
            assert all(c is not None for c in configs)
            seen += [json.dumps(c, sort_keys=True) for c in configs]
            for k in order:
                searcher.on_trial_complete(ids[k], {"objective": float(len(seen[-2 + k]) % 7)})
        return seen

    first = suggestions([0, 1])
    assert first == suggestions([1, 0]) and len(set(first)) == 6
    # from_defaults (the default): configuration 0 is the method's own values
    assert json.loads(first[0]) == plan.searches["asp"].defaults() == {
        k: getattr(plan.searches["asp"].cells[0], k) for k in ranges}
    plan.settings = dataclasses.replace(plan.settings, from_defaults=False)
    assert suggestions([0, 1])[0] != first[0]


# ---- the report's tuning section -----------------------------------------------------------------------------
def test_the_tuning_tables_name_each_methods_best_and_the_spread_of_its_search(tmp_path):
    from asp_dist.analysis.tuning import best_table, plot_tuning, spread_table

    configs = pd.DataFrame({
        "run": "r", "method": ["pc"] * 4 + ["asp"] * 4, "configuration": [0, 1, 2, 3] * 2,
        "knob_lr": [1e-3, 2e-3, 3e-3, 4e-3] * 2, "objective": [0.5, 0.7, 0.7, float("nan"), 2.0, 1.0, 3.0, 1.5],
        "higher_is_better": False})
    best = best_table(configs).set_index("method")
    assert best.loc["pc", "best_configuration"] == 0 and best.loc["pc", "values"] == "lr=0.001"  # lower is better
    assert best.loc["asp", "best_configuration"] == 1 and best.loc["asp", "configuration_0"] == 2.0
    spread = spread_table(configs).set_index("method")
    assert spread.loc["pc", "n"] == 3 and spread.loc["pc", "max"] == 0.7 and spread.loc["pc", "last_improved_at"] == 0
    assert spread.loc["asp", "last_improved_at"] == 1 and spread.loc["asp", "median"] == 1.75
    (figure,) = plot_tuning(configs.assign(higher_is_better=False), tmp_path)
    assert figure.name == "tuning_r" and all(p.is_file() for p in figure.paths)


# ---- a real run, killed and resumed -------------------------------------------------------------------------
@pytest.mark.slow
def test_tune_killed_and_resumed_evaluates_no_configuration_or_cell_twice(tmp_path):
    """SIGKILL the tune run once some cells have rows, run it again: every method ends with exactly its budget
    of configurations, each configuration's cells have one row each, rows written before the kill are never
    rewritten, and the report names each method's best configuration as space settings."""
    results, ray_temp = tmp_path / "runs", f"/tmp/asp-tk-{os.getpid()}"  # Ray's socket paths are short
    args = ("tune", "tune-smoke", "--results", str(results), "--ray-temp-dir", ray_temp)
    sweep_dir = results / "tune-smoke"
    try:
        proc = start_cli(*args, log_dir=tmp_path / "log1")
        wait_for(lambda: len(parquet_files(sweep_dir)) >= 6, 300, while_alive=proc)
        kill_group(proc)  # SIGKILL: the driver and its process group
        assert proc.wait(30) == -signal.SIGKILL, read_log(tmp_path / "log1")
        wait_until_gone(proc.pid, ray_temp, 60)
        before = {f: f.stat().st_mtime_ns for f in parquet_files(sweep_dir)}
        again = cli(*args, timeout=400)
    finally:
        shutil.rmtree(ray_temp, ignore_errors=True)
    assert again.returncode == 0, again.stderr[-3000:]
    assert {f: f.stat().st_mtime_ns for f in before} == before, "a row written before the kill was rewritten"
    table = pd.read_parquet(sweep_dir / "configurations.parquet")
    assert table.groupby("method").size().to_dict() == {"asp": 3, "osp": 3, "pc": 3}
    assert table["objective"].notna().all() and (table["cells_done"] == 4).all()
    cells = [cid for ids in table["cell_ids"] for cid in ids.split(",")]
    rows = {f.stem for f in parquet_files(sweep_dir)}
    assert len(cells) == len(set(cells)) == 36 and rows == set(cells), "a cell outside the configurations, or twice"
    tuned = tomllib.loads((sweep_dir / "tuned.toml").read_text())["methods"]
    assert set(tuned) == {"pc", "osp", "asp"} and set(tuned["asp"]) == {"lr", "lambda_unpaired"}
    best = table.loc[table[table["method"] == "pc"]["objective"].idxmax()]
    assert tuned["pc"]["lr"] == pytest.approx(best["knob_lr"])
    assert "best configuration" in again.stderr
    status = cli("status", "tune-smoke", "--results", str(results), timeout=60)
    assert status.returncode == 2 and "is a tune run (asp-dist tune), not a sweep" in status.stderr
    # The stats job reads a tune run as a sweep, with a tuning section
    stats = cli("stats", "tune-smoke", "--results", str(results), "--formats", "md", timeout=300)
    assert stats.returncode == 0, stats.stderr[-2000:]
    report = (sweep_dir / "report.md").read_text()
    assert "## Tuning: every method on the same budget" in report and (sweep_dir / "figures" / "tuning_tune-smoke.png").is_file()
    # The tuned settings are a space's settings
    path = space(tmp_path, f'settings = ["{sweep_dir / "tuned.toml"}"]\n'
                 + GRID.replace("first = 100, last = 101", "first = 1000, last = 1000"), "confirm.toml")
    assert [c.lr for c in expand(path) if c.method == "pc"] == [pytest.approx(tuned["pc"]["lr"])] * 2
