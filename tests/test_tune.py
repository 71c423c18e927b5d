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
from budgets import TINY
from harness import cli, kill_group, parquet_files, read_log, space, start_cli, wait_for, wait_until_gone
from planted import raw_pickle

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
    ("scheduler = 'hyperband'", "scheduler must be one of none, asha, got 'hyperband'"),
    ("grace_points = 5", 'grace_points is an ASHA setting, which needs scheduler = "asha"'),
    ("scheduler = 'asha'\ngrace_points = 0", "grace_points must be an integer >= 1, got 0"),
    ("scheduler = 'asha'\ngrace_points = 2.5", "grace_points must be an integer >= 1, got 2.5"),
    ("scheduler = 'asha'\nreduction_factor = 1", "reduction_factor must be a number above 1, got 1"),
    ("scheduler = 'asha'\nreduction_factor = 'half'", "reduction_factor must be a number above 1"),
    ("scheduler = 'asha'\nbrackets = 0", "brackets must be an integer >= 1, got 0"),
    ("scheduler = 'asha'\ngrace_points = 51", "grace_points is 51, beyond the 50 curve points a cell"),
])
def test_bad_tune_tables_are_refused_in_one_line(tmp_path, table, message):
    with pytest.raises(SweepError, match=re.escape(message)):
        plan_of(tmp_path, table)


def test_asha_is_a_tune_option_and_a_run_without_it_keeps_its_fingerprint(tmp_path):
    plan = plan_of(tmp_path, "budget = 4\nscheduler = 'asha'\ngrace_points = 5\nreduction_factor = 2\n")
    assert (plan.settings.scheduler, plan.settings.grace_points, plan.settings.reduction_factor,
            plan.settings.brackets) == ("asha", 5, 2.0, 1)
    legacy = 'objective = "pooled_median"\ncommon_seeds = false\ntop_k = 0\n'
    plain = plan_of(tmp_path, "budget = 4\n" + legacy)
    assert plain.settings.scheduler == "none"
    # Without a scheduler and the validation stage, the settings a run records (and fingerprints) are those of
    # a run made before either existed: such a run resumes. ASHA's knobs are part of an ASHA run's fingerprint.
    assert plain.settings.record() == {"budget": 4, "search": "tpe", "seed": 0, "metric": "mixed",
                                       "from_defaults": True}
    assert plan.fingerprint() != plain.fingerprint()
    other = plan_of(tmp_path, "budget = 4\nscheduler = 'asha'\ngrace_points = 10\nreduction_factor = 2\n")
    assert other.fingerprint() != plan.fingerprint()


def test_a_tune_run_validates_on_trials_of_its_own_with_common_seeds_by_default(tmp_path):
    """The defaults: stage 2 on the 20 trials after the calibration's (102-121 here), the top 3 of each search and its
    default, every configuration of a method on the same seeds (the cells' common_seeds knob), and the objective
    per paired count; each is recorded, so a run with other settings has another fingerprint."""
    plan = plan_of(tmp_path, "budget = 4\n")
    settings = plan.settings
    assert (settings.top_k, settings.objective, settings.common_seeds) == (3, "median_per_paired", True)
    assert settings.validation_trials == tuple(range(102, 122))
    search = plan.searches["osp"]
    assert all(c.common_seeds for c in search.cells + search.validation_cells)
    assert sorted({c.trial for c in search.validation_cells}) == list(range(102, 122))
    assert len(search.validation_cells) == 2 * 20 and {c.paired for c in search.validation_cells} == {2, 8}
    # Two configurations of one method draw the same training and evaluation randomness; other methods do not
    a, b = search.configuration({"lr": 1e-3, "lambda_paired": 1.0})[0], search.configuration({"lr": 5e-3,
                                                                                              "lambda_paired": 3.0})[0]
    assert a.cell_id != b.cell_id and a.seed_for("train") == b.seed_for("train") and a.seed_for("eval") == b.seed_for("eval")
    assert plan.searches["pc"].cells[0].seed_for("train") != search.cells[0].seed_for("train")
    assert settings.record()["validation_trials"] == list(range(102, 122))
    ranged = plan_of(tmp_path, "budget = 4\ntop_k = 2\nvalidation_trials = { first = 500, last = 509 }\n")
    assert ranged.settings.validation_trials == tuple(range(500, 510)) and ranged.fingerprint() != plan.fingerprint()
    pooled = plan_of(tmp_path, "budget = 4\nobjective = 'pooled_median'\n")
    assert pooled.fingerprint() != plan.fingerprint()


@pytest.mark.parametrize("table,message", [
    ("budget = 3\ntop_k = 3\n", "top_k (3) must be below the budget (3)"),
    ("top_k = -1\n", "top_k is how many search configurations"),
    ("top_k = 0\nvalidation_trials = 5\n", "validation_trials is a stage-2 setting, which top_k = 0 turns off"),
    ("validation_trials = 0\n", "validation_trials is a number of trials (>= 1)"),
    ("validation_trials = { first = 9, last = 3 }\n", "validation_trials is a number of trials"),
    ("validation_trials = 950\n", "validation trials must lie in 100-999 (1000 and up are confirmatory); they reach "
                                   "1000, 1001"),
    ("validation_trials = { first = 101, last = 120 }\n", "validation trials 101 are calibration trials too"),
    ("objective = 'mean'\n", "objective must be one of median_per_paired, pooled_median"),
    ("common_seeds = 1\n", "common_seeds must be true or false"),
])
def test_bad_validation_settings_are_refused_in_one_line(tmp_path, table, message):
    with pytest.raises(SweepError, match=re.escape(message)):
        plan_of(tmp_path, table)


@pytest.mark.parametrize("values,rule,expected", [
    ([(2, 1.0), (2, 3.0), (2, 5.0), (4, 10.0)], "median_per_paired", (3.0 + 10.0) / 2),
    ([(2, 1.0), (2, 3.0), (2, 5.0), (4, 10.0)], "pooled_median", 4.0),
    # a count where every cell failed: the configuration is not judged on the other counts alone
    ([(2, 1.0), (4, None), (4, float("nan"))], "median_per_paired", float("nan")),
    ([(2, 1.0), (4, None)], "pooled_median", 1.0),
    ([(2, None)], "pooled_median", float("nan")),
])
def test_a_configurations_objective_sees_every_paired_count(values, rule, expected):
    """A setting that collapses at one paired count cannot win on the pooled median of the others."""
    from asp_dist.sweep.tune_plan import configuration_objective

    got = configuration_objective(values, rule)
    assert (got != got and expected != expected) or got == pytest.approx(expected)


def test_the_candidates_are_the_default_then_the_best_others_and_stage_two_ties_go_to_the_default(tmp_path):
    from asp_dist.sweep.tune_validation import candidates

    plan = plan_of(tmp_path, "budget = 6\ntop_k = 2\n")
    default = plan.searches["pc"].default_values()["lr"]
    rows = pd.DataFrame({"method": "pc", "configuration": range(6),
                         "knob_lr": [default, 2e-3, 3e-3, 2e-3, 5e-3, 6e-3],
                         "objective": [0.9, 0.5, 0.7, 0.95, float("nan"), 0.8],
                         "default": [True, False, False, False, False, False]})
    chosen = candidates(plan, pd.concat([rows, rows.assign(method="osp", knob_lambda_paired=1.0,
                                                           default=False)]))["pc"]
    # the default first (the search's best, 3, is not the default); 1 repeats 3's values; 4 has no objective
    assert [(c.configuration, c.default) for c in chosen] == [(0, True), (3, False), (5, False)]
    assert [c.search_objective for c in chosen] == [0.9, 0.95, 0.8]


def test_a_stage_is_done_when_its_records_hold_its_budget_and_else_runs_again_in_a_new_experiment(tmp_path):
    """What makes a resumed tune run skip a method's search or validation: the records of its latest experiment."""
    from asp_dist.sweep.tuning import RECORDS, SEARCH, VALIDATION, method_experiment

    records = tmp_path / "tune" / RECORDS
    assert method_experiment(tmp_path, "all", 2, VALIDATION) == ("validate-all", False)
    (records / "validate-all").mkdir(parents=True)
    (tmp_path / "tune" / "validate-all").mkdir()  # Tune's folder of the stopped experiment
    record = {"trial_id": "x", "status": "TERMINATED", "values": {"candidate": 0}, "result": {}}
    (records / "validate-all" / "0.json").write_text(json.dumps({"number": 0, **record}))
    assert method_experiment(tmp_path, "all", 2, VALIDATION) == ("validate-all-2", False)  # one of two: again
    (records / "validate-all" / "1.json").write_text(json.dumps({"number": 1, **record}))
    assert method_experiment(tmp_path, "all", 2, VALIDATION) == ("validate-all", True)
    assert method_experiment(tmp_path, "all", 2, SEARCH) == ("tune-all", False)  # the stages are apart


def test_tuning_happens_on_calibration_trials_only(tmp_path):
    with pytest.raises(SweepError, match=r"tune on calibration trials \(100-999\); its grid has trial\(s\) 1000, 1001"):
        plan_of(tmp_path, "budget = 2", GRID.replace("first = 100, last = 101", "first = 1000, last = 1001"))
    with pytest.raises(SweepError, match="a tune run searches one domain's methods"):
        plan_of(tmp_path, "budget = 2", GRID.replace('domain = ["signaling"]', 'domain = ["signaling", "levers"]'))
    with pytest.raises(SweepError, match="it has no \\[tune\\] table"):
        TunePlan.from_space(space(tmp_path, GRID))
    with pytest.raises(SweepError, match=r"a tune run searches methods, not arms \(osp@default\)"):
        plan_of(tmp_path, "budget = 2", GRID.replace('"osp", "asp"', '"osp", "osp@default", "asp"'))


def test_the_cli_refuses_a_bad_tune_space_in_one_line_and_writes_nothing(tmp_path):
    bad = space(tmp_path, GRID + "\n[tune]\nbudget = 0\n")
    out = cli("tune", bad, "--results", str(tmp_path / "runs"), timeout=60)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and out.stderr.startswith("asp-dist: error: ")
    assert "budget" in out.stderr and not (tmp_path / "runs").exists()
    good = space(tmp_path, GRID + "\n[tune]\nbudget = 2\n", "good.toml")
    out = cli("tune", good, "--results", str(tmp_path / "runs"), "--budget", "0", timeout=60)
    assert out.returncode == 2 and "--budget" in out.stderr and not (tmp_path / "runs").exists()
    out = cli("tune", good, "--results", str(tmp_path / "runs"), "--scheduler", "hyperband", timeout=60)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "--scheduler must be one of none, asha" \
        in out.stderr and not (tmp_path / "runs").exists()
    asha = space(tmp_path, GRID + "\n[tune]\nbudget = 2\nscheduler = 'asha'\nreduction_factor = 0.5\n", "asha.toml")
    out = cli("tune", asha, "--results", str(tmp_path / "runs"), timeout=60)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and out.stderr.startswith("asp-dist: error: ")
    assert "reduction_factor must be a number above 1" in out.stderr and not (tmp_path / "runs").exists()
    broken = space(tmp_path, GRID + "\n[tune\nbudget = 2\n", "broken.toml")
    out = cli("tune", broken, "--results", str(tmp_path / "runs"), timeout=60)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "invalid TOML in" in out.stderr
    assert not (tmp_path / "runs").exists()


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


# ---- ASHA: early stopping on the configurations' learning curves -----------------------------------------
def test_a_configuration_reports_the_median_probe_once_every_cell_has_closed_a_curve_point():
    from types import SimpleNamespace

    from asp_dist.sweep.tuning import CurveObjective

    reports = []
    curve = CurveObjective({"a": 2, "b": 2, "c": 2}, "probe_mixed", reports.append)
    cell = {c: SimpleNamespace(cell_id=c) for c in "abcz"}
    point = lambda v=None: {"step": 1.0} if v is None else {"step": 1.0, "probe_mixed": v}
    curve.seed("c", [None, 0.9, 0.5])  # a cell with a row: its stored curve
    curve([(cell["a"], [point(), point(0.2)]), (cell["z"], [point(5.0)])])  # z: not of this configuration
    assert reports == []  # b has closed no point yet
    curve([(cell["b"], [point(), point(0.4), point(0.7)])])
    # point 1 carries no probe: nothing to report; point 2: the median over the three cells
    assert reports == [{"objective": 0.4, "curve_point": 2}]
    curve([(cell["a"], [point(float("nan"))])])
    assert reports[-1] == {"objective": 0.6, "curve_point": 3}  # NaN-safe: a's NaN left out
    # A pack that trains a member with a row again passes its points on from the first: each is reported once
    curve([(cell["c"], [point(), point(0.9), point(0.5), point()])])
    assert len(reports) == 2
    curve([(cell["a"], [point(float("nan"))]), (cell["b"], [point(float("nan"))])])
    assert len(reports) == 2 and curve.reported == 4  # no finite value at point 4: nothing to report
    # By paired count: a curve point's objective is the mean of each count's median, as a finished one's is
    by_count = []
    curve = CurveObjective({"a": 2, "b": 2, "c": 4}, "probe_mixed", by_count.append, "median_per_paired")
    curve([(cell["a"], [point(0.2)]), (cell["b"], [point(0.4)]), (cell["c"], [point(1.0)])])
    assert by_count == [{"objective": pytest.approx((0.3 + 1.0) / 2), "curve_point": 1}]


def test_asha_sees_only_curve_point_results_and_never_stops_a_configuration_at_its_last_point(tmp_path):
    """What the tune run relies on in Ray's ASHAScheduler: a result without curve_point (a checkpoint's, with
    its NaN objective; the final report) is passed over and reaches no rung; the last curve point does not
    stop a configuration by itself (its cells still have to be evaluated and written)."""
    from types import SimpleNamespace

    from ray.tune.schedulers import TrialScheduler

    from asp_dist.sweep.tuning import _scheduler

    plan = plan_of(tmp_path, "budget = 4\nscheduler = 'asha'\ngrace_points = 5\nreduction_factor = 2\n")
    asha = _scheduler(plan, plan.searches["pc"])
    asha.set_search_properties("objective", "max")
    assert [m for m, _ in asha._brackets[0]._rungs] == [40, 20, 10, 5]  # 50 curve points at train_steps 150
    good, bad = SimpleNamespace(trial_id="good"), SimpleNamespace(trial_id="bad")
    for trial in (good, bad):
        asha.on_trial_add(None, trial)
    assert asha.on_trial_result(None, bad, {"objective": float("nan"), "step": 30}) == TrialScheduler.CONTINUE
    assert all(not recorded for _, recorded in asha._brackets[0]._rungs)
    assert asha.on_trial_result(None, good, {"objective": 0.6, "curve_point": 5}) == TrialScheduler.CONTINUE
    assert asha.on_trial_result(None, good, {"objective": 0.7, "curve_point": 50}) == TrialScheduler.CONTINUE
    assert asha.on_trial_result(None, bad, {"objective": 0.3, "curve_point": 5}) == TrialScheduler.STOP
    assert asha.on_trial_result(None, good, {"objective": 0.7, "cells_done": 4}) == TrialScheduler.CONTINUE
    assert _scheduler(plan_of(tmp_path, "budget = 4\n"), plan.searches["pc"]) is None  # FIFO: today's run


TINY_PARTICLES = "[[grid]]\n[grid.fixed]\n" + "\n".join(f"{k} = {v!r}" for k, v in TINY["particles"].items()) + """
[grid.axes]
domain = ["particles"]
method = ["pc"]
paired = [4]
trial = { first = 100, last = 101 }

[tune]
budget = 4
seed = 0
scheduler = "asha"
grace_points = 1
reduction_factor = 2
top_k = 0  # the search alone: stage 2 is the tune-smoke run's
[tune.ranges]
lr = { log_uniform = [1e-5, 1e-1] }
"""


def test_asha_stops_hopeless_configurations_which_write_no_rows_and_are_never_chosen_or_run_again(tmp_path):
    """A real tune run with an aggressive ASHA (grace 1, reduction factor 2) on tiny particle cells (40 curve
    points each; a configuration is one pack of 2 cells): some configurations are stopped on their learning curves; each
    counts once against the budget, has no rows and no objective, is marked with where it was stopped, and
    tuned.toml takes the best of those that finished. Run again, the run trains nothing: a stopped
    configuration (TERMINATED in Tune's state) is not resumed."""
    results, ray_temp = tmp_path / "runs", f"/tmp/asp-ta-{os.getpid()}"  # Ray's socket paths are short
    args = ("tune", space(tmp_path, TINY_PARTICLES, "asha.toml"), "--results", str(results), "--workers", "1",
            "--ray-temp-dir", ray_temp)
    sweep_dir = results / "asha"
    try:
        out = cli(*args, timeout=300)
        assert out.returncode == 0, out.stderr[-3000:]
        rows = {f: f.stat().st_mtime_ns for f in parquet_files(sweep_dir)}
        again = cli(*args, timeout=300)
    finally:
        shutil.rmtree(ray_temp, ignore_errors=True)
    assert again.returncode == 0, again.stderr[-3000:]
    table = pd.read_parquet(sweep_dir / "configurations.parquet")
    assert len(table) == 4 and list(table["configuration"]) == [0, 1, 2, 3]
    stopped, finished = table[table["stopped_early"]], table[~table["stopped_early"]]
    assert len(stopped) >= 1 and len(finished) >= 1
    assert stopped["objective"].isna().all() and stopped["objective_at_stop"].notna().all()
    assert stopped["stopped_at_point"].between(1, 40).all() and (stopped["cells_done"] == 0).all()
    assert finished["objective"].notna().all() and (finished["cells_done"] == 2).all()
    assert finished["stopped_at_point"].isna().all()
    written = {f.stem for f in rows}
    assert written == {c for ids in finished["cell_ids"] for c in ids.split(",")}, "a stopped configuration's row"
    assert not list((sweep_dir / "tune").rglob(".ckpt-tmp/*")), "a checkpoint left staged"
    tuned = tomllib.loads((sweep_dir / "tuned.toml").read_text())["methods"]
    assert tuned["pc"]["lr"] == pytest.approx(finished.loc[finished["objective"].idxmax(), "knob_lr"])
    assert f"ASHA stopped {len(stopped)} of 4 pc configurations early" in out.stderr
    assert "stopped by ASHA at curve point" in out.stderr
    # Run again: nothing trained, nothing rewritten, the same table (the stopped ones still stopped)
    assert {f: f.stat().st_mtime_ns for f in parquet_files(sweep_dir)} == rows
    assert "configurations, last" not in again.stderr  # no configuration completed in the second run
    pd.testing.assert_frame_equal(pd.read_parquet(sweep_dir / "configurations.parquet"), table)


def test_the_tuning_section_counts_the_configurations_asha_stopped_and_never_names_one_best():
    from asp_dist.analysis.document import Text
    from asp_dist.analysis.tuning import best_table, spread_table, tuning_blocks

    plain = pd.DataFrame({"run": "plain", "method": "pc", "configuration": [0, 1], "knob_lr": [1e-3, 2e-3],
                          "objective": [0.5, 0.6], "higher_is_better": True})
    asha = pd.DataFrame({"run": "asha", "method": ["pc"] * 4, "configuration": [0, 1, 2, 3],
                         "knob_lr": [1e-3, 2e-3, 3e-3, 4e-3], "objective": [0.5, float("nan"), 0.4, 0.9],
                         "stopped_early": [False, True, False, True], "higher_is_better": True})
    # (a stopped configuration has no objective; 0.9 here checks that it is left out even if it had one)
    configs = pd.concat([plain, asha], ignore_index=True)
    best = best_table(configs).set_index("run")
    assert best.loc["asha", "best_configuration"] == 0 and best.loc["asha", "stopped_early"] == 2
    assert best.loc["plain", "best_configuration"] == 1 and best.loc["plain", "stopped_early"] == 0
    assert "stopped_early" not in best_table(plain)  # a run without ASHA: today's table
    assert spread_table(configs).set_index("run").loc["asha", "n"] == 2
    assert any(isinstance(b, Text) and "stopped_early" in b.md for b in tuning_blocks(configs))
    assert not any(isinstance(b, Text) and "stopped_early" in b.md for b in tuning_blocks(plain))


# ---- a real run, killed and resumed -------------------------------------------------------------------------
@pytest.mark.slow
def test_tune_killed_and_resumed_evaluates_no_configuration_or_cell_twice(tmp_path):
    """SIGKILL the tune run once some cells have rows, run it again: every method ends with exactly its budget
    of configurations and then its default and best configuration validated on trials of their own, each
    configuration's cells have one row each, rows written before the kill are never rewritten, tuned.toml holds
    each method's validation winner as space settings, and both stages' records say they are done. Tune's own state is
    never unpickled on the way: pickles planted where Tune keeps it (tuner.pkl, a searcher's state), which
    Tuner.restore would load, run nothing."""
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
        experiments = [d for d in (sweep_dir / "tune").glob("tune-*") if d.is_dir()]
        assert experiments, "no Tune experiment to plant into"
        for experiment in experiments:
            for name in ("tuner.pkl", "searcher-state-2099-01-01_00-00-00.pkl"):
                (experiment / name).write_bytes(raw_pickle(tmp_path / "ran"))
        again = cli(*args, timeout=400)
    finally:
        shutil.rmtree(ray_temp, ignore_errors=True)
    assert again.returncode == 0, again.stderr[-3000:]
    assert not (tmp_path / "ran").exists(), "resuming the tune run unpickled a file planted in Tune's state"
    assert {f: f.stat().st_mtime_ns for f in before} == before, "a row written before the kill was rewritten"
    table = pd.read_parquet(sweep_dir / "configurations.parquet")
    search, validation = table[table["stage"] == "search"], table[table["stage"] == "validation"]
    assert search.groupby("method").size().to_dict() == {"asp": 3, "osp": 3, "pc": 3}
    assert table["objective"].notna().all() and (search["cells_done"] == 4).all()
    # Stage 2: each method's default and its search's best other configuration, on trials 102-103 only
    assert validation.groupby("method").size().to_dict() == {"asp": 2, "osp": 2, "pc": 2}
    assert (validation["cells_done"] == 4).all() and validation.groupby("method")["default"].sum().eq(1).all()
    cells = [cid for ids in table["cell_ids"] for cid in ids.split(",")]
    trials = {stage: {int(re.search(r"-t(\d+)-", c).group(1)) for ids in rows["cell_ids"] for c in ids.split(",")}
              for stage, rows in table.groupby("stage")}
    assert trials == {"search": {100, 101}, "validation": {102, 103}}
    rows = {f.stem for f in parquet_files(sweep_dir)}
    # a search configuration with the default's values trains the same cells as the search's configuration 0
    assert len(set(cells)) == 36 + 24 and rows == set(cells), "a cell outside the configurations"
    assert len(search["cell_ids"].str.split(",").explode()) == 36, "a search cell twice"
    # tuned.toml holds each method's validation winner, the configuration marked chosen
    tuned = tomllib.loads((sweep_dir / "tuned.toml").read_text())["methods"]
    assert set(tuned) == {"pc", "osp", "asp"} and set(tuned["asp"]) == {"lr", "lambda_unpaired"}
    for method, mine in validation.groupby("method"):
        best = mine.loc[mine["objective"].idxmax()]  # the signaling game: higher is better
        assert bool(best["chosen"]) and mine["chosen"].sum() == 1
        assert tuned[method]["lr"] == pytest.approx(best["knob_lr"])
    assert not search["chosen"].any()
    assert "chosen on validation trials 102-103" in (sweep_dir / "tuned.toml").read_text()
    assert "won validation" in again.stderr
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
    # Both stages' records say they are done: a run again starts no Tune experiment (tested without Ray below)
    from asp_dist.sweep.tuning import VALIDATION, method_experiment
    assert method_experiment(sweep_dir, "all", 6, VALIDATION)[1]  # one experiment: 3 methods × 2 candidates


@pytest.mark.parametrize("higher", [True, False])
def test_the_winning_configuration_is_the_best_finished_one_ties_to_the_lowest_index(higher):
    """One rule for tuned.toml, the tuning report and bench/asha_saving.py: the best objective among the
    configurations that trained to their end, ties to the lowest index whatever the table's row order."""
    from asp_dist.sweep.tune_plan import winning_configuration

    best, worse = (5.0, 1.0) if higher else (1.0, 5.0)
    table = pd.DataFrame({"configuration": [3, 1, 2, 0, 4],
                          "objective": [best, best, worse, float("nan"), 2 * best if higher else 0.0],
                          "stopped_early": [False, False, False, False, True]})
    assert int(winning_configuration(table, higher)["configuration"]) == 1  # 4 is better but was stopped
    assert int(winning_configuration(table.drop(columns="stopped_early"), higher)["configuration"]) == 4
    assert winning_configuration(table[table["objective"].isna()], higher) is None
