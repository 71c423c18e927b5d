"""The report's tuning section: the expected best objective against the budget, the validation stage's tables, the
per-configuration values, and the "What was run" table of a tune run; and which of a tune run's rows the statistics
compare (no Ray, no training)."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from asp_dist.analysis.document import Document, Text, render_markdown
from asp_dist.analysis.tuning import (
    best_table,
    configuration_tables,
    expected_best,
    expected_best_summary,
    expected_best_table,
    plot_expected_best,
    spread_table,
    tuning_blocks,
    validation_tables,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "results" / "examples"


def _enumerated(values: list[float], n: int, higher: bool) -> tuple[float, float]:
    """The best of n draws with replacement, over every one of the N^n equally likely draws."""
    pick = max if higher else min
    best = np.array([pick(draw) for draw in itertools.product(values, repeat=n)])
    return float(best.mean()), float(best.std())


# ---- the expected best of n configurations --------------------------------------------------------------------
@pytest.mark.parametrize("higher", [True, False])
@pytest.mark.parametrize("values", [[0.3, 0.1, 0.7, 0.5], [2.0, 2.0, -1.0, 5.0, 0.0], [1.5]])
def test_the_expected_best_is_the_mean_and_sd_of_the_best_of_n_draws_enumerated(values, higher):
    curve = expected_best(values, higher).set_index("n")
    assert list(curve.index) == list(range(1, len(values) + 1))
    for n in curve.index:
        mean, sd = _enumerated(values, n, higher)
        assert curve.loc[n, "mean"] == pytest.approx(mean, abs=1e-12)
        assert curve.loc[n, "sd"] == pytest.approx(sd, abs=1e-9)


def test_one_draw_gives_the_mean_many_give_the_best_and_the_curve_never_falls():
    rng = np.random.default_rng(0)
    values = rng.normal(size=30)
    up, down = expected_best(values, True), expected_best(values, False)
    assert up["mean"].iloc[0] == pytest.approx(values.mean()) == down["mean"].iloc[0]
    assert up["sd"].iloc[0] == pytest.approx(values.std())
    assert np.all(np.diff(up["mean"]) >= -1e-12) and np.all(np.diff(down["mean"]) <= 1e-12)  # lower is better
    # n → ∞: every draw reaches the best (the formula holds for any n, not only n ≤ N)
    assert (values.max() - up["mean"].iloc[-1]) > 0 and up["mean"].iloc[-1] > up["mean"].iloc[len(values) // 2]
    many = np.sort(values)
    far = float(sum(v * ((i / 30) ** 10_000 - ((i - 1) / 30) ** 10_000) for i, v in enumerate(many, 1)))
    assert far == pytest.approx(values.max())


def test_the_expected_best_leaves_out_missing_values_and_is_empty_without_any():
    pd.testing.assert_frame_equal(expected_best([0.2, np.nan, 0.4]), expected_best([0.4, 0.2]))
    assert expected_best([np.nan]).empty and list(expected_best([]).columns) == ["n", "mean", "sd"]


def test_stopped_configurations_count_at_the_objective_asha_stopped_them_at():
    configs = pd.DataFrame({
        "run": "r", "method": ["pc"] * 4 + ["osp"] * 2, "configuration": [0, 1, 2, 3, 0, 1],
        "objective": [0.5, np.nan, 0.4, np.nan, np.nan, np.nan],
        "stopped_early": [False, True, False, True, True, False],
        "objective_at_stop": [np.nan, 0.9, np.nan, np.nan, np.nan, np.nan],  # configuration 3: stopped, no value
        "higher_is_better": True})
    table = expected_best_table(configs)
    assert set(table["method"]) == {"pc"}  # osp has no value at all: left out
    pc = table.set_index("n")
    assert pc["configurations"].iloc[0] == 3 and pc["at_stop"].iloc[0] == 1
    pd.testing.assert_series_equal(pc["mean"], expected_best([0.5, 0.9, 0.4]).set_index("n")["mean"])
    assert any(isinstance(b, Text) and "objective_at_stop" in b.md for b in tuning_blocks(configs))


def test_the_summary_shows_powers_of_two_below_the_budget_and_the_budget_itself():
    configs = pd.DataFrame({"run": "r", "method": ["pc"] * 6 + ["asp"] * 3, "configuration": [*range(6), *range(3)],
                            "objective": [3.0, 1.0, 2.0, 5.0, 4.0, 0.0, 1.0, 1.0, 1.0], "higher_is_better": False})
    summary = expected_best_summary(configs).set_index("method")
    assert [c for c in summary.columns if c.startswith("n=")] == ["n=1", "n=2", "n=4", "n=N"]
    assert summary.loc["asp", "n=4"] == "–" and summary.loc["asp", "n=N"] == "1 ± 0"
    assert summary.loc["pc", "n=1"].startswith("2.5 ± ")  # the mean of the six
    assert summary.loc["asp", "gain after N/2"] == "–"  # every value the same: no rise to share


def test_the_expected_best_figure_has_a_panel_per_run(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    configs = pd.DataFrame({"run": ["a"] * 4 + ["b"] * 3, "method": ["pc", "pc", "asp", "asp", "pc", "pc", "pc"],
                            "configuration": [0, 1, 0, 1, 0, 1, 2], "objective": [1.0, 2.0, 3.0, 0.5, 4.0, 5.0, 6.0],
                            "higher_is_better": [False] * 4 + [True] * 3})
    (figure,) = plot_expected_best(configs, tmp_path)
    assert figure.name == "tuning_expected_best" and all(p.is_file() for p in figure.paths)
    assert plot_expected_best(configs.assign(objective=np.nan), tmp_path) == []


# ---- the validation stage, and a file written before it ----------------------------------------------------------
def _search() -> pd.DataFrame:
    return pd.DataFrame({"run": "r", "method": ["pc"] * 4, "configuration": [0, 1, 2, 3],
                         "knob_lr": [1e-3, 2e-3, 3e-3, 4e-3], "knob_lambda_paired": np.nan,
                         "objective": [0.5, 0.7, 0.2, 0.6], "cells": 2, "cells_done": 2,
                         "cell_ids": ["a,b", "c,d", "e,f", "g,h"], "higher_is_better": True})


def _staged() -> pd.DataFrame:
    """_search with the validation stage as `asp-dist tune` writes it: the default and the best two again on held-out
    trials (`configuration` nullable: a default the search did not try has none)."""
    search = _search().assign(stage="search", default=[True, False, False, False])
    validation = pd.DataFrame({"run": "r", "method": ["pc"] * 3, "stage": "validation",
                               "configuration": pd.array([0, 1, 3], dtype="Int64"), "candidate": [0, 1, 2],
                               "default": [True, False, False], "knob_lr": [1e-3, 2e-3, 4e-3],
                               "knob_lambda_paired": np.nan, "objective": [0.6, 0.55, 0.65],
                               "search_objective": [0.5, 0.7, 0.6], "cells": 2, "cells_done": 2,
                               "cell_ids": ["m,n", "i,j", "k,l"], "chosen": [False, False, True],
                               "higher_is_better": True})
    return pd.concat([search, validation], ignore_index=True)


def _markdown(blocks) -> str:
    return render_markdown(Document("t", Path("."), list(blocks)))


def test_a_table_without_stages_and_its_search_stage_give_the_same_search_tables():
    plain, staged = _search(), _staged()
    pd.testing.assert_frame_equal(best_table(plain), best_table(staged))
    pd.testing.assert_frame_equal(spread_table(plain), spread_table(staged))
    pd.testing.assert_frame_equal(expected_best_table(plain), expected_best_table(staged))
    for (_, _, a), (_, _, b) in zip(configuration_tables(plain), configuration_tables(staged), strict=True):
        pd.testing.assert_frame_equal(a, b)
    assert validation_tables(plain) == []
    # the search's blocks read the same; the validation's come after the spread, the rest as before
    old, new = _markdown(tuning_blocks(plain)), _markdown(tuning_blocks(staged))
    start = new.index("### Validation on held-out trials")
    end = new.index("### Expected best objective")
    assert new[:start] + new[end:] == old and "| 3 | 0.6 | 0.65 | ✓ |" in new[start:end]


def test_the_validation_table_shows_search_and_validation_objectives_and_the_pick():
    ((run, method, line, table),) = validation_tables(_staged())
    assert (run, method) == ("r", "pc")
    assert list(table["configuration"]) == ["0 (default)", "1", "3"]
    assert list(table["search_objective"]) == [0.5, 0.7, 0.6] and list(table["validation_objective"]) == [0.6, 0.55, 0.65]
    assert list(table["chosen"]) == ["", "", "✓"]
    assert "chose configuration 3" in line and "the default did not win" in line
    # a default the search did not try, without a search_objective column, wins: its search objective is the
    # search's default row's (none here: "–"), and the line says the default won
    staged = _staged().drop(columns="search_objective")
    staged["configuration"] = staged["configuration"].astype("Int64")
    staged.loc[4, "configuration"] = pd.NA
    staged.loc[:3, "default"] = False
    staged["chosen"] = [False] * 4 + [True, False, False]
    ((_, _, line, table),) = validation_tables(staged)
    assert table["configuration"].iloc[0] == "default" and np.isnan(table["search_objective"].iloc[0])
    assert list(table["search_objective"].iloc[1:]) == [0.7, 0.6]  # found by index in the search
    assert "chose the default" in line and "the default won" in line


def test_every_configuration_table_has_each_searched_knob_and_asha_stops():
    ((_, _, plain),) = configuration_tables(_search())
    assert list(plain.columns) == ["configuration", "lr", "objective"]  # lambda_paired: not searched by pc
    asha = _search().assign(stopped_early=[False, True, False, False], stopped_at_point=pd.array([None, 5, None, None],
                                                                                                  dtype="Int64"),
                            objective_at_stop=[np.nan, 0.3, np.nan, np.nan])
    ((_, _, table),) = configuration_tables(asha)
    assert np.isnan(table["objective"].iloc[1]) and table["stopped"].iloc[1] == "at point 5: 0.3"


# ---- a real tune run's report -------------------------------------------------------------------------------
def _tune_run_result(sweep_dir: Path):
    """A StatsResult for a committed tune run, light enough for a fast test: the real configurations.parquet and
    tune-plan.json (what the tuning section and "What was run" read), and one row per cell its configurations
    trained, with the configuration's knob values (the rows' own, which decide the treatments), the statistics
    tables left empty (the sections that read them say so)."""
    from asp_dist.analysis.job import StatsResult
    from asp_dist.analysis.layout import domain_layout, label_rows
    from asp_dist.analysis.tables import StatsConfig
    from asp_dist.results.query import Inputs

    configs = pd.read_parquet(sweep_dir / "configurations.parquet")
    domain = json.loads((sweep_dir / "tune-plan.json").read_text())["domain"]
    rows = []
    for rec in configs.to_dict("records"):
        for j, cell in enumerate(rec["cell_ids"].split(",")):
            rows.append({"domain": domain, "method": rec["method"], "paired": int(re.search(r"-p(\d+)-", cell)[1]),
                         "trial": 300 + j % 5, "root_seed": 0, "cell_id": cell, "sweep_id": sweep_dir.name,
                         **{k[5:]: v for k, v in rec.items() if k.startswith("knob_")},
                         "eval_mixed": rec["objective"], "eval_mixed_higher_is_better": False})
    rows = pd.DataFrame(rows)
    layout = domain_layout(rows, "eval_mixed")
    summary = pd.DataFrame(columns=["domain", "condition", "treatment", "paired", "n", "median", "q1", "q3", "ci_low",
                                    "ci_high", "mean", "std"])
    tables = {name: pd.DataFrame() for name in ("tests", "pairwise", "by_paired", "efficiency", "claim_2n",
                                                "knob_trend", "missing")}
    return StatsResult(StatsConfig(), label_rows(rows, layout, "eval_mixed"), {domain: layout},
                       {**tables, "summary": summary}, Inputs(files=[], sweep_dirs=[sweep_dir]))


def _table_cells(markdown: str, heading: str) -> list[str]:
    section = markdown.split(heading, 1)[1].split("\n## ", 1)[0]
    return [cell.strip() for line in section.splitlines() if line.startswith("|") for cell in line.split(" | ")]


def test_a_tune_runs_report_names_its_configurations_and_shows_the_expected_best(tmp_path):
    from asp_dist.analysis.report import build_report, grid_description

    result = _tune_run_result(EXAMPLES / "tune-levers")
    text = render_markdown(build_report(result, tmp_path))
    cells = _table_cells(text, "## What was run")
    assert cells and max(len(c) for c in cells) <= 300
    grid = grid_description(result).iloc[0]
    assert grid["methods"] == "pc, osp, asp"
    assert grid["varied knobs"] == ("pc: configurations 0–23; osp: configurations 0–23; asp: configurations 0–23 "
                                    "(tuning section)")
    assert "### Expected best objective against the budget" in text
    expected = text.split("### Expected best objective against the budget", 1)[1]
    assert "| run | method | configurations | n=1 | n=2 | n=4 | n=8 | n=16 | n=N | gain after N/2 |" in expected
    assert "| tune-levers | asp | 24 |" in expected and "### Every configuration tried" in text
    assert "| configuration | lr | lambda_paired | lambda_unpaired | adversary_loss |" in text


def test_a_sweeps_what_was_run_still_lists_its_knobs():
    from asp_dist.analysis.report import grid_description

    result = _tune_run_result(EXAMPLES / "tune-levers")
    listed = grid_description(result, pd.DataFrame()).iloc[0]  # no configurations: read as a sweep's rows
    assert listed["methods"].startswith("pc, osp[lambda_paired=") and listed["varied knobs"].startswith("lr = ")


# ---- the rows a tune run's statistics compare ---------------------------------------------------------------
def _cell_rows(sweep_dir: Path) -> pd.DataFrame:
    """One row per cell of every configuration of a committed tune run (either stage), paired and trial read from
    the cell id, the configuration's knob values, and a metric that differs from row to row: what tune_run_rows
    reads of the rows, without reading ~2,000 files."""
    configs = pd.read_parquet(sweep_dir / "configurations.parquet")
    rng = np.random.default_rng(0)
    rows = []
    for rec in configs.to_dict("records"):
        for cell in rec["cell_ids"].split(","):
            paired, trial = map(int, re.search(r"-p(\d+)-t(\d+)-", cell).groups())
            rows.append({"domain": "levers", "method": rec["method"], "paired": paired, "trial": trial,
                         "root_seed": 0, "cell_id": cell, **{k[5:]: v for k, v in rec.items() if k.startswith("knob_")},
                         "eval_mixed": rec["objective"] + rng.normal(0, 0.01), "eval_mixed_higher_is_better": False})
    return pd.DataFrame(rows)


def _cells_of(configs: pd.DataFrame, method_of) -> dict[str, str]:
    return {c: method_of(rec) for rec in configs.to_dict("records") for c in rec["cell_ids"].split(",")}


def test_a_validated_tune_runs_statistics_compare_each_chosen_setting_with_its_default(tmp_path):
    from asp_dist.analysis.job import tune_run_rows
    from asp_dist.analysis.layout import domain_layout, label_rows, treatment_order
    from asp_dist.analysis.tables import StatsConfig, default_vs_tuned_table

    run = EXAMPLES / "tune-validated-levers"
    configs = pd.read_parquet(run / "configurations.parquet")
    validation = configs[configs["stage"] == "validation"]
    lost = validation[validation["default"] & ~validation["chosen"]]  # the defaults, none of which won
    expected = {**_cells_of(lost, lambda r: f"{r['method']}@default"),
                **_cells_of(validation[validation["chosen"]], lambda r: r["method"])}
    rows = _cell_rows(run)
    kept, note = tune_run_rows(rows, run)
    assert len(kept) == len(expected) == 600 and dict(zip(kept["cell_id"], kept["method"])) == expected
    layout = domain_layout(kept, "eval_mixed")
    labelled = label_rows(kept, layout, "eval_mixed")
    assert layout.shared_knobs == [] and set(labelled["condition"]) == {"all"}
    assert treatment_order(labelled["treatment"]) == ["pc", "pc@default", "osp", "osp@default", "asp", "asp@default"]
    dvt = pd.DataFrame(default_vs_tuned_table(labelled, StatsConfig(), layout))
    assert list(zip(dvt["tuned"], dvt["default"], dvt["n_blocks"])) == [
        ("pc", "pc@default", 100), ("osp", "osp@default", 100), ("asp", "asp@default", 100)]
    assert note == ("tune-validated-levers is a tune run: the statistics below compare each method's setting chosen "
                    "on the validation trials (PC configuration 14, OSP configuration 12, ASP configuration 17) and "
                    "its default (`<method>@default`) where another setting won: 600 of its 3,000 rows. Every "
                    "configuration is in the tuning section.")
    # a default that wins has no arm of its own: it is the method's tuned setting
    won = configs.assign(chosen=configs["chosen"].where(configs["method"] != "pc", configs["default"]
                                                        & configs["stage"].eq("validation")))
    kept, note = tune_run_rows(rows, _with_configurations(run, won, tmp_path))
    assert set(kept["method"]) == {"pc", "osp", "osp@default", "asp", "asp@default"} and "PC its default" in note


def _with_configurations(run: Path, configs: pd.DataFrame, tmp_path: Path) -> Path:
    """A directory named as run, with its tune-plan.json and the given configurations.parquet."""
    where = tmp_path / run.name
    where.mkdir()
    (where / "tune-plan.json").write_text((run / "tune-plan.json").read_text())
    configs.to_parquet(where / "configurations.parquet")
    return where


def test_a_tune_run_without_validation_compares_each_methods_search_winner():
    from asp_dist.analysis.job import tune_run_rows
    from asp_dist.analysis.layout import domain_layout, label_rows, treatment_order

    run = EXAMPLES / "tune-levers"
    configs = pd.read_parquet(run / "configurations.parquet")
    assert "stage" not in configs
    # lower error is better; ties would go to the lower index
    best = configs.sort_values(["method", "objective", "configuration"]).groupby("method", sort=False).head(1)
    kept, note = tune_run_rows(_cell_rows(run), run)
    assert dict(zip(kept["cell_id"], kept["method"])) == _cells_of(best, lambda r: r["method"])
    assert sorted(best["configuration"]) == [11, 12, 15] and len(kept) == 75
    labelled = label_rows(kept, layout := domain_layout(kept, "eval_mixed"), "eval_mixed")
    assert set(labelled["condition"]) == {"all"} and treatment_order(labelled["treatment"]) == ["pc", "osp", "asp"]
    assert not any(layout.method_knobs.values())
    assert "without a validation stage" in note and "PC configuration 12, OSP configuration 11, ASP configuration 15" \
        in note and "75 of its 1,800 rows" in note


def test_a_sweeps_rows_are_not_narrowed():
    from asp_dist.analysis.job import tune_run_rows

    rows = _cell_rows(EXAMPLES / "tune-levers")
    same, note = tune_run_rows(rows, EXAMPLES / "confirm-levers")  # a sweep: no configurations.parquet
    assert same is rows and note == ""


def _copy_cells(source: Path, target: Path, cell_ids) -> None:
    for cell in cell_ids:
        (found,) = source.glob(f"cells/*/*/{cell}.parquet")
        (target / found.relative_to(source)).parent.mkdir(parents=True, exist_ok=True)
        (target / found.relative_to(source)).write_bytes(found.read_bytes())


def test_the_stats_job_narrows_a_tune_runs_rows_only(tmp_path):
    """A small copy of tune-validated-levers (its validation cells of two trials and a few search cells) beside a
    sweep holding two of its cells: the tune run's rows are narrowed, the sweep's all kept, duplicates dropped."""
    from asp_dist.analysis.job import read_rows, run_stats
    from asp_dist.analysis.tables import StatsConfig
    from asp_dist.results.query import open_inputs

    source = EXAMPLES / "tune-validated-levers"
    configs = pd.read_parquet(source / "configurations.parquet")
    validation = configs[configs["stage"] == "validation"]
    run, sweep = tmp_path / "tune-validated-levers", tmp_path / "sweep"
    run.mkdir()
    for name in ("configurations.parquet", "tune-plan.json"):
        (run / name).write_bytes((source / name).read_bytes())
    chosen = [c for ids in validation.loc[validation["chosen"], "cell_ids"] for c in ids.split(",")
              if re.search(r"-t40[56]-", c)]
    defaults = [c for ids in validation.loc[validation["default"], "cell_ids"] for c in ids.split(",")
                if re.search(r"-t40[56]-", c)]
    others = [c for ids in validation.loc[~validation["default"] & ~validation["chosen"], "cell_ids"]
              for c in ids.split(",") if re.search(r"-t405-", c)]
    search = configs.loc[configs["stage"].eq("search") & configs["cells_done"].gt(0), "cell_ids"].iloc[0].split(",")[:5]
    _copy_cells(source, run, chosen + defaults + others + search)
    _copy_cells(source, sweep, [others[0], chosen[0]])  # a sweep that ran one dropped cell and one kept cell
    rows, notes = read_rows(open_inputs([run, sweep]))
    assert sorted(rows["cell_id"]) == sorted(chosen + defaults + [others[0], chosen[0]])
    assert rows.loc[rows["cell_id"] == others[0], "method"].tolist() == [others[0].split("-")[1]]  # the sweep's
    assert notes == [f"tune-validated-levers is a tune run: the statistics below compare each method's setting "
                     f"chosen on the validation trials (PC configuration 14, OSP configuration 12, ASP configuration "
                     f"17) and its default (`<method>@default`) where another setting won: 60 of its "
                     f"{len(chosen + defaults + others + search)} rows. Every configuration is in the tuning section."]
    next(sweep.glob(f"cells/*/*/{others[0]}.parquet")).unlink()  # a knob varied within pc would split it
    result = run_stats([run, sweep], StatsConfig(n_boot=100))
    assert result.rows["cell_id"].is_unique and len(result.rows) == len(chosen + defaults)  # the cell in both: once
    assert any("duplicate row(s) of 1 cell id(s)" in n for n in result.notes) and result.tune_notes == notes
    assert set(result.rows["treatment"]) == {"pc", "pc@default", "osp", "osp@default", "asp", "asp@default"}
    assert list(result.tables["default_vs_tuned"]["tuned"]) == ["pc", "osp", "asp"]


def test_the_report_says_at_its_top_which_rows_of_a_tune_run_it_compares(tmp_path):
    from asp_dist.analysis.report import build_report

    result = _tune_run_result(EXAMPLES / "tune-levers")
    result.tune_notes = ["tune-levers is a tune run: the statistics below compare this and that."]
    text = render_markdown(build_report(result, tmp_path))
    assert text.index("tune-levers is a tune run: the statistics below") < text.index("## At a glance")
