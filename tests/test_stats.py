"""The statistics job on synthetic rows with known answers.

`make_rows` / `write_sweep` build sweeps without training anything; test_query.py and
test_plots.py import them from here.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from asp_dist.analysis.job import compute, run_stats, write_tables
from asp_dist.analysis.rank_tests import bootstrap_median_ci, friedman, holm, nemenyi, quartiles, wilcoxon
from asp_dist.analysis.tables import StatsConfig
from asp_dist.errors import SchemaError, SpecError
from asp_dist.results import store
from asp_dist.results.query import load_rows, open_inputs
from asp_dist.spec import FIELD_NAMES

EFFECT = {"pc": 0.0, "osp": 0.5, "asp": 1.0}


def make_rows(domain: str = "signaling", methods=("pc", "osp", "asp"), paired=(0, 1, 2, 4), trials=range(8),
              effect: dict | None = None, noise: float = 0.3, higher: bool = True, seed: int = 0,
              knobs: dict | None = None, sweep_id: str = "synthetic") -> list[dict]:
    """Rows like run_cell's: metric = trial effect + method effect + noise (negated when lower is better)."""
    effect = EFFECT if effect is None else effect
    rng = np.random.default_rng(seed)
    knob_grid = [{}] if not knobs else [dict(zip(knobs, vals)) for vals in
                                        pd.MultiIndex.from_product(list(knobs.values())).tolist()]
    rows = []
    for kv in knob_grid:
        for t in trials:
            for p in paired:
                block = rng.normal() + 0.1 * p
                for m in methods:
                    value = block + effect.get(m, 0.0) + noise * rng.normal()
                    kv_text = "-".join(f"{k}{v}" for k, v in kv.items())
                    rows.append({
                        "domain": domain, "method": m, "paired": p, "trial": t, "root_seed": 0,
                        "lambda_unpaired": 1.0 if m == "asp" else 0.0, "train_steps": 100,
                        **kv,
                        "cell_id": f"{domain}-{m}-p{p}-t{t}-{kv_text or 'x'}",
                        "eval_mixed": value if higher else -value,
                        "eval_self_play_base": 3.0 if higher else 0.0,
                        "eval_self_play_new": 2.0 if higher else 1.0,  # a finished row has every required metric
                        "eval_mixed_higher_is_better": higher,
                        "metric_directions": json.dumps({"mixed": "higher" if higher else "lower"}),
                        "figure_data": None, "sweep_id": sweep_id,
                    })
    return rows


def write_sweep(root: Path, rows: list[dict], manifest_ids: list[str] | None = None,
                planned: list[dict] | None = None) -> Path:
    """A sweep directory of `rows`. Its manifest: `planned` rows as the sweep service writes them
    (ids and their specs), or `manifest_ids` as an old manifest (ids only), or none."""
    root.mkdir(parents=True, exist_ok=True)
    for row in rows:
        d = root / "cells" / f"domain={row['domain']}" / f"method={row['method']}"
        d.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist([row]), d / f"{row['cell_id']}.parquet")
    if planned is not None:
        (root / "manifest.json").write_text(json.dumps({
            "name": root.name, "cells": [r["cell_id"] for r in planned],
            "specs": [{k: v for k, v in r.items() if k in FIELD_NAMES} for r in planned]}))
    elif manifest_ids is not None:
        (root / "manifest.json").write_text(json.dumps({"name": root.name, "cells": manifest_ids, "specs": []}))
    return root


def cfg(**kw) -> StatsConfig:
    return StatsConfig(n_boot=500, **kw)


# ---- small statistics with known answers ------------------------------------------------------------

def test_quartiles_known_values():
    assert quartiles(range(1, 10)) == (3.0, 5.0, 7.0)
    assert quartiles([1, 2, 3, 4]) == (1.75, 2.5, 3.25)


def test_friedman_matches_published_example():
    # Pulse rates of 7 subjects at three times (scipy.stats.friedmanchisquare documentation):
    # chi2 = 10.571, p = 0.00506.
    before = [72, 96, 88, 92, 74, 76, 82]
    after = [120, 120, 132, 120, 101, 96, 112]
    later = [76, 95, 104, 96, 84, 72, 76]
    stat, p = friedman(np.array([before, after, later]).T)
    assert stat == pytest.approx(10.5714, abs=1e-4)
    assert p == pytest.approx(0.0050634, abs=1e-6)
    nem = nemenyi(np.array([before, after, later]).T)
    assert nem.shape == (3, 3) and nem[0, 1] < 0.01 < nem[0, 2]


def test_friedman_without_ties_equals_textbook_formula():
    rng = np.random.default_rng(1)
    scores = rng.normal(size=(12, 3))
    ranks = scores.argsort(axis=1).argsort(axis=1) + 1
    n, k = scores.shape
    expected = 12 / (n * k * (k + 1)) * (ranks.sum(axis=0) ** 2).sum() - 3 * n * (k + 1)
    assert friedman(scores)[0] == pytest.approx(expected)


def test_all_ties_give_no_evidence():
    assert friedman(np.ones((5, 3))) == (0.0, 1.0)
    assert wilcoxon(np.zeros(6)) == (0.0, 1.0)
    assert np.all(nemenyi(np.ones((5, 3))) == 1.0)


def test_holm_known_values():
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    out = holm([0.2, np.nan, 0.01])
    assert out[0] == pytest.approx(0.2) and np.isnan(out[1]) and out[2] == pytest.approx(0.02)


def test_bootstrap_is_reproducible_and_brackets_the_median():
    x = np.random.default_rng(3).normal(size=25)
    a = bootstrap_median_ci(x, 1000, 0.95, seed=7)
    assert a == bootstrap_median_ci(x, 1000, 0.95, seed=7)
    assert a != bootstrap_median_ci(x, 1000, 0.95, seed=8)
    assert a[0] <= np.median(x) <= a[1]
    assert bootstrap_median_ci([2.0], seed=1) == (2.0, 2.0)


# ---- the job on synthetic sweeps ------------------------------------------------------------------

def test_summary_matches_direct_computation():
    rows = pd.DataFrame(make_rows())
    res = compute(rows, cfg())
    s = res.tables["summary"]
    assert len(s) == 3 * 4 and set(s["n"]) == {8}
    g = rows[(rows.method == "asp") & (rows.paired == 2)]["eval_mixed"]
    rec = s[(s.treatment == "asp") & (s.paired == 2)].iloc[0]
    assert rec["median"] == pytest.approx(g.median())
    assert (rec["q1"], rec["q3"]) == pytest.approx(tuple(np.percentile(g, [25, 75])))
    assert rec["mean"] == pytest.approx(g.mean()) and rec["std"] == pytest.approx(g.std(ddof=1))
    assert rec["ci_low"] <= rec["median"] <= rec["ci_high"]


def test_bootstrap_interval_of_a_group_does_not_depend_on_other_groups():
    rows = pd.DataFrame(make_rows())
    full = compute(rows, cfg()).tables["summary"]
    only_asp = compute(rows[rows.method == "asp"], cfg()).tables["summary"]
    a = full[full.treatment == "asp"].set_index("paired")[["ci_low", "ci_high"]]
    b = only_asp.set_index("paired")[["ci_low", "ci_high"]]
    pd.testing.assert_frame_equal(a, b)


def test_clear_effect_is_detected_with_asp_best():
    res = compute(pd.DataFrame(make_rows(paired=(2, 3, 4))), cfg())
    tests = res.tables["tests"].iloc[0]
    assert tests["test"] == "friedman" and tests["p_value"] < 1e-6 and tests["n_blocks"] == 24
    pw = res.tables["pairwise"].set_index(["a", "b"])
    assert pw.loc[("asp", "pc"), "significant"] and pw.loc[("asp", "pc"), "better"] == "asp"
    assert pw.loc[("asp", "osp"), "significant"] and pw.loc[("asp", "osp"), "better"] == "asp"
    assert pw.loc[("asp", "pc"), "median_diff"] == pytest.approx(1.0, abs=0.3)
    assert json.loads(tests["mean_ranks"])["asp"] < json.loads(tests["mean_ranks"])["pc"]


def test_nemenyi_decides_and_wilcoxon_holm_is_the_second_view():
    # ASP = OSP + 0.1 in 10 blocks, equal in 11, 0.05 worse in 3; PC far behind. The signed-rank test
    # sees 10 of 13 non-zero differences favour ASP; Nemenyi's mean ranks (1.35 vs 1.65) do not separate them.
    rows = pd.DataFrame(make_rows(paired=(0, 1, 2), noise=0.0))
    rows["eval_mixed"] = rows["method"].map({"pc": 0.0, "osp": 1.0, "asp": 1.0})
    asp = rows.index[rows.method == "asp"]
    rows.loc[asp, "eval_mixed"] += [0.1] * 10 + [0.0] * 11 + [-0.05] * 3
    res = compute(rows, cfg())
    pw = res.tables["pairwise"].set_index(["a", "b"]).loc[("asp", "osp")]
    assert pw["p_nemenyi"] > 0.05 and pw["p_holm"] < 0.05
    assert not pw["significant"] and pw["significant_wilcoxon_holm"] and not pw["views_agree"]
    assert res.tables["pairwise"].set_index(["a", "b"]).loc[("asp", "pc"), "significant"]


def test_identical_methods_are_not_significant():
    same = {"pc": 0.0, "osp": 0.0, "asp": 0.0}
    res = compute(pd.DataFrame(make_rows(effect=same, noise=0.0)), cfg())
    assert res.tables["tests"].iloc[0]["p_value"] == 1.0
    assert not res.tables["pairwise"]["significant"].any()
    assert (res.tables["pairwise"]["better"] == "tie").all()
    noisy = compute(pd.DataFrame(make_rows(effect=same, noise=0.3, seed=5)), cfg())
    assert noisy.tables["tests"].iloc[0]["p_value"] > 0.05
    assert not noisy.tables["pairwise"]["significant"].any()


def test_lower_is_better_comes_from_the_rows():
    # Metric negated and flagged lower-is-better: ASP has the lowest values and must still win.
    rows = pd.DataFrame(make_rows(domain="vae", paired=(8, 16, 32), higher=False))
    res = compute(rows, cfg())
    assert res.layouts["vae"].higher_is_better is False
    pw = res.tables["pairwise"].set_index(["a", "b"])
    assert pw.loc[("asp", "pc"), "better"] == "asp" and pw.loc[("asp", "pc"), "median_diff"] < 0
    # Without the flag column, the direction is read from metric_directions.
    res2 = compute(rows.drop(columns="eval_mixed_higher_is_better"), cfg())
    assert res2.layouts["vae"].higher_is_better is False
    with pytest.raises(SpecError, match="higher or lower"):
        compute(rows.drop(columns=["eval_mixed_higher_is_better", "metric_directions"]), cfg())


def test_paper_paired_range_is_used_per_domain():
    rows = pd.DataFrame(make_rows(domain="particles", paired=range(0, 7)))
    res = compute(rows, cfg())
    t = res.tables["tests"].iloc[0]
    assert t["paired_range"] == "2-4" and t["n_blocks"] == 3 * 8
    res = compute(rows, cfg(paired_ranges={"particles": (0, 6)}))
    assert res.tables["tests"].iloc[0]["n_blocks"] == 7 * 8


def test_two_methods_use_the_wilcoxon_test():
    res = compute(pd.DataFrame(make_rows(methods=("osp", "asp"))), cfg())
    t = res.tables["tests"].iloc[0]
    assert t["test"] == "wilcoxon" and t["p_value"] < 0.01
    assert len(res.tables["pairwise"]) == 1 and res.tables["pairwise"].iloc[0]["a"] == "asp"


def test_shared_knob_is_a_condition_and_method_only_knob_a_treatment():
    rows = make_rows(knobs={"signaling_skew": [0.0, 2.0]})
    extra = [dict(r, lambda_unpaired=0.5, cell_id=r["cell_id"] + "-l05") for r in rows if r["method"] == "asp"]
    res = compute(pd.DataFrame(rows + extra), cfg())
    layout = res.layouts["signaling"]
    assert layout.shared_knobs == ["signaling_skew"]
    assert layout.method_knobs["asp"] == ["lambda_unpaired"] and layout.method_knobs["pc"] == []
    assert set(res.tables["summary"]["condition"]) == {"signaling_skew=0", "signaling_skew=2"}
    assert set(res.tables["summary"]["treatment"]) == {"pc", "osp", "asp[lambda_unpaired=0.5]", "asp[lambda_unpaired=1]"}
    assert len(res.tables["tests"]) == 2 and (res.tables["tests"]["test"] == "friedman").all()


def test_efficiency_threshold_and_two_n_claim():
    # Deterministic medians: value = method level + 0.1*paired (noise 0 and the block term removed).
    rows = pd.DataFrame(make_rows(paired=(0, 1, 2, 4), noise=0.0))
    block = rows.groupby(["trial", "paired"])["eval_mixed"].transform("min")  # = pc value of the block
    rows["eval_mixed"] = rows["eval_mixed"] - block + 0.1 * rows["paired"]
    # pc = 0.1p, osp = 0.5 + 0.1p, asp = 1 + 0.1p
    res = compute(rows, cfg(thresholds={"signaling": 0.7}))
    eff = res.tables["efficiency"].set_index("treatment")
    assert eff.loc["asp", "min_paired_reaching"] == 0
    assert eff.loc["osp", "min_paired_reaching"] == 2
    assert pd.isna(eff.loc["pc", "min_paired_reaching"])
    claim = res.tables["claim_2n"].set_index(["other", "n"])
    assert claim.loc[("osp", 1), "holds"] and claim.loc[("osp", 2), "holds"]  # 1.1 >= 0.7, 1.2 >= 0.9
    assert claim.loc[("pc", 2), "median_gain"] == pytest.approx(1.2 - 0.4)
    assert claim.loc[("pc", 2), "verdict"].startswith("beats")
    # ASP made worse than OSP with twice the data: the claim fails.
    rows.loc[rows.method == "asp", "eval_mixed"] -= 0.9
    claim = compute(rows, cfg()).tables["claim_2n"].set_index(["other", "n"])
    assert not claim.loc[("osp", 2), "holds"] and claim.loc[("osp", 2), "verdict"] == "falls short"


def test_two_n_gain_is_positive_when_asp_is_better_whichever_way_the_metric_points():
    # The same outcomes stored once as a score (higher is better) and once negated as an error (lower is
    # better): ASP's gain over the others, its interval and the verdict must not change sign with the direction.
    gains = {}
    for higher in (True, False):
        rows = pd.DataFrame(make_rows(domain="levers", paired=(1, 2, 4), higher=higher,
                                      effect={"pc": 0.0, "osp": 0.5, "asp": 5.0}))
        claim = compute(rows, cfg()).tables["claim_2n"].set_index(["other", "n"])
        rec = claim.loc[("pc", 2)]
        assert rec["verdict"].startswith("beats") and rec["median_gain"] > 0 and rec["gain_ci_low"] > 0
        assert (claim["verdict"].str.startswith("beats") == (claim["gain_ci_low"] > 0)).all()
        assert ((claim["gain_ci_low"] <= claim["median_gain"]) & (claim["median_gain"] <= claim["gain_ci_high"])).all()
        gains[higher] = claim[["median_gain", "gain_ci_low", "gain_ci_high", "verdict"]]
    pd.testing.assert_frame_equal(gains[True], gains[False])


def test_default_threshold_is_ninety_percent_of_base():
    res = compute(pd.DataFrame(make_rows()), cfg())
    eff = res.tables["efficiency"]
    assert eff["threshold"].iloc[0] == pytest.approx(2.7) and "90%" in eff["threshold_rule"].iloc[0]


def test_duplicate_rows_are_dropped_with_a_note():
    rows = make_rows(trials=range(3))
    res = compute(pd.DataFrame(rows + rows[:5]), cfg())
    assert len(res.rows) == len(rows) and any("duplicate" in n for n in res.notes)


# ---- partial, merged and mismatched inputs ----------------------------------------------------------

def test_partial_sweep_reports_missing_cells_and_incomplete_blocks(tmp_path):
    rows = make_rows(trials=range(4))
    boom = make_rows(methods=("asp",), paired=(8,), trials=range(1))[0] | {"cell_id": "signaling-asp-p8-t0-abcdef"}
    done = [r for r in rows if not (r["method"] == "pc" and r["trial"] == 3)]
    sweep = write_sweep(tmp_path / "partial", done, planned=rows + [boom])
    failed = sweep / "failed"
    failed.mkdir()
    (failed / "signaling-asp-p8-t0-abcdef.json").write_text(json.dumps(
        {"cell_id": "signaling-asp-p8-t0-abcdef", "error": "Traceback ...\nRuntimeError: boom"}))
    res = run_stats([sweep], cfg())
    missing = res.tables["missing"]
    manifest_missing = missing[missing.kind != "incomplete block"]
    assert len(manifest_missing) == 4 + 1
    assert set(manifest_missing[manifest_missing.kind == "not finished (manifest)"]["method"]) == {"pc"}
    boom = manifest_missing[manifest_missing.kind == "failed"].iloc[0]
    assert boom["paired"] == 8 and boom["error"] == "RuntimeError: boom"
    incomplete = missing[missing.kind == "incomplete block"]
    assert len(incomplete) == 4 and set(incomplete["trial"]) == {3}
    assert any("44 of 49 planned cells finished" in n for n in res.notes) and res.grid_known
    # The stats still run on the complete blocks.
    assert res.tables["tests"].iloc[0]["n_blocks_incomplete"] == 4


def test_missing_cells_are_described_from_the_manifest_specs(tmp_path):
    rows = make_rows(trials=range(2), knobs={"signaling_skew": [0.0, 2.0]})
    gone = rows.pop()  # the last cell never finished
    sweep = write_sweep(tmp_path / "specs", rows)
    planned = rows + [gone]
    (sweep / "manifest.json").write_text(json.dumps({
        "cells": [r["cell_id"] for r in planned],
        "specs": [{k: r[k] for k in ("domain", "method", "paired", "trial", "signaling_skew")} for r in planned]}))
    missing = run_stats([sweep], cfg()).tables["missing"]
    rec = missing[missing.kind == "not finished (manifest)"].iloc[0]
    assert rec["cell_id"] == gone["cell_id"] and rec["condition"] == "signaling_skew=2"
    assert (rec["method"], rec["paired"], rec["trial"]) == (gone["method"], gone["paired"], gone["trial"])


def test_failed_cells_are_reported_without_a_manifest(tmp_path):
    sweep = write_sweep(tmp_path / "nomanifest-failed", make_rows(trials=range(2)))
    (sweep / "failed").mkdir()
    (sweep / "failed" / "signaling-pc-p8-t0-ffff.json").write_text(json.dumps({"error": "ValueError: nan loss"}))
    missing = run_stats([sweep], cfg()).tables["missing"]
    assert missing.iloc[0]["kind"] == "failed" and missing.iloc[0]["error"] == "ValueError: nan loss"


def test_missing_cell_of_an_old_manifest_is_not_guessed_from_its_id(tmp_path):
    # Manifests from before the specs were stored hold ids only: the cell is listed by id, described by its
    # failure record when there is one, and its paired count and trial stay unknown (no parsing of the id).
    rows = make_rows(trials=range(2))
    sweep = write_sweep(tmp_path / "old", rows, manifest_ids=[r["cell_id"] for r in rows]
                        + ["signaling-pc-p8-t0-0123456789", "signaling-osp-p8-t0-9876543210"])
    store.record_failure(sweep, "signaling-osp-p8-t0-9876543210", "signaling", "osp", "Traceback\nValueError: x")
    missing = run_stats([sweep], cfg()).tables["missing"].set_index("cell_id")
    never = missing.loc["signaling-pc-p8-t0-0123456789"]
    assert never["kind"] == "not finished (manifest)" and pd.isna(never["method"]) and pd.isna(never["paired"])
    failed = missing.loc["signaling-osp-p8-t0-9876543210"]
    assert failed["kind"] == "failed" and failed["error"] == "ValueError: x"
    assert (failed["domain"], failed["method"]) == ("signaling", "osp") and pd.isna(failed["paired"])


def test_unreadable_manifest_is_a_note_not_a_crash(tmp_path):
    sweep = write_sweep(tmp_path / "badmanifest", make_rows(trials=range(2)))
    (sweep / "manifest.json").write_text("{not json")
    res = run_stats([sweep], cfg())
    assert any("manifest.json cannot be read" in n for n in res.notes) and not res.grid_known


def test_sweep_without_manifest_still_runs(tmp_path):
    sweep = write_sweep(tmp_path / "nomanifest", make_rows(trials=range(3)))
    res = run_stats([sweep], cfg())
    assert any("no manifest.json" in n for n in res.notes) and not res.grid_known
    assert res.tables["missing"].empty


def test_merged_sweeps_keep_each_domain_and_direction(tmp_path):
    a = write_sweep(tmp_path / "sig", make_rows(trials=range(3), sweep_id="sig"))
    b = write_sweep(tmp_path / "vae", make_rows(domain="vae", paired=(8, 16, 32), trials=range(3), higher=False,
                                                knobs={"vae_latent_dim": [2, 32]}, sweep_id="vae"))
    res = run_stats([a, b], cfg())
    assert set(res.layouts) == {"signaling", "vae"}
    assert res.layouts["vae"].higher_is_better is False and res.layouts["vae"].shared_knobs == ["vae_latent_dim"]
    assert set(res.tables["tests"]["paired_range"]) == {"0-4", "8-32"}
    out = write_tables(res, tmp_path / "merged")
    back = pd.read_parquet(out["summary"])
    assert len(back) == len(res.tables["summary"]) and (tmp_path / "merged/stats/summary.md").read_text().startswith("|")


def test_mismatched_column_types_are_refused(tmp_path):
    rows = make_rows(trials=range(2))
    sweep = write_sweep(tmp_path / "bad", rows)
    bad = dict(rows[0], eval_mixed="0.5", cell_id="odd")
    odd = tmp_path / "odd.parquet"  # a loose file given beside the sweep (inside it, it would not count)
    pq.write_table(pa.Table.from_pylist([bad]), odd)
    with pytest.raises(SchemaError, match="column 'eval_mixed' is float in .* but string in"):
        run_stats([sweep, odd], cfg())


def test_files_without_key_columns_are_refused(tmp_path):
    sweep = write_sweep(tmp_path / "nokeys", make_rows(trials=range(2)))
    pq.write_table(pa.table({"x": [1]}), tmp_path / "stray.parquet")
    with pytest.raises(SchemaError, match="lacks the key column"):
        open_inputs([sweep, tmp_path / "stray.parquet"])


def test_int_and_float_columns_widen_and_temp_files_are_ignored(tmp_path):
    rows = make_rows(trials=range(2))
    sweep = write_sweep(tmp_path / "widen", rows)
    widened = tmp_path / "w.parquet"
    pq.write_table(pa.Table.from_pylist([dict(rows[0], train_steps=1.5, cell_id="w")]), widened)
    (sweep / "cells" / ".half-written.parquet").write_bytes(b"garbage")
    (sweep / "cells" / "_tmp").mkdir()
    (sweep / "cells" / "_tmp" / "x.parquet").write_bytes(b"garbage")
    df = load_rows([sweep, widened])
    assert len(df) == len(rows) + 1 and df["train_steps"].dtype == float


def test_missing_metric_column_is_a_clear_error():
    with pytest.raises(SpecError, match="metric column 'eval_nope'"):
        compute(pd.DataFrame(make_rows(trials=range(2))), cfg(metric="eval_nope"))


def test_real_run_cell_rows_go_through_the_whole_job(tmp_path):
    """Rows from run_cell itself (tiny signaling cells), stored as the sweep service stores them."""
    from asp_dist.commands.stats import run_stats_job
    from asp_dist.spec import CellSpec
    from asp_dist.training.cell import run_cell

    sweep = tmp_path / "real"
    ids = []
    for trial in range(2):
        for paired in (0, 2):
            for method in ("pc", "osp", "asp"):
                spec = CellSpec(domain="signaling", method=method, paired=paired, trial=trial, train_steps=40,
                                batch_size=16, unpaired_size=64)
                row = dict(run_cell(spec), sweep_id="real")
                row["torch_version"] = str(row["torch_version"])
                table = pa.Table.from_pylist([row])
                for col in ("domain", "method"):  # the store keeps these dictionary-encoded
                    table = table.set_column(table.schema.get_field_index(col), col,
                                             table.column(col).dictionary_encode())
                d = sweep / "cells" / "domain=signaling" / f"method={method}"
                d.mkdir(parents=True, exist_ok=True)
                pq.write_table(table, d / f"{row['cell_id']}.parquet")
                ids.append(row["cell_id"])
    (sweep / "manifest.json").write_text(json.dumps({"cells": ids + ["signaling-asp-p4-t0-0000000000"]}))
    report = run_stats_job([str(sweep)], cfg=cfg(), figures=False, log=lambda m: None)
    text = report.read_text()
    assert "12 rows" in text and "signaling-asp-p4-t0-0000000000" in text
    summary = pd.read_parquet(sweep / "stats" / "summary.parquet")
    assert set(summary["treatment"]) == {"pc", "osp", "asp"} and set(summary["n"]) == {2}
    assert summary["higher_is_better"].all()


def test_conditions_are_in_natural_order():
    rows = pd.DataFrame(make_rows(domain="vae", paired=(32,), trials=range(2), higher=False,
                                  knobs={"vae_latent_dim": [2, 16, 128, 8]}))
    res = compute(rows, cfg())
    expected = [f"vae_latent_dim={d}" for d in (2, 8, 16, 128)]
    assert list(res.tables["tests"]["condition"]) == expected
    assert list(dict.fromkeys(res.tables["summary"]["condition"])) == expected


# ---- the outputs: report.md, report.html, stats/*.tex ---------------------------------------------------

def _tex_rows(tex: str) -> tuple[str, list[list[str]]]:
    """A booktabs tabular's column spec and its rows split into cells (a `\\&` is text, not a separator)."""
    spec = re.search(r"\\begin\{tabular\}\{([a-z]+)\}", tex).group(1)
    body = tex[tex.index(r"\toprule"):tex.index(r"\bottomrule")]
    rows = []
    for line in body.splitlines():
        line = line.strip()
        if line in (r"\toprule", r"\midrule") or not line:
            continue
        assert line.endswith(r"\\"), line
        rows.append(re.split(r"(?<!\\)&", line[:-2]))
    return spec, rows


def _braces_balance(tex: str) -> bool:
    depth = 0
    for text in re.sub(r"\\[{}]", "", tex).replace("\\\\", ""):
        depth += {"{": 1, "}": -1}.get(text, 0)
        if depth < 0:
            return False
    return depth == 0


@pytest.fixture(scope="module")
def latex_result(tmp_path_factory):
    """A lower-is-better domain whose labels hold LaTeX specials: a condition and a treatment with `_`."""
    from asp_dist.analysis.latex_tables import write_latex_tables

    rows = make_rows(trials=range(6), higher=False, knobs={"signaling_skew": [0.0, 1.5]})
    rows += [dict(r, method="asp", cell_id=r["cell_id"] + "-l5", lambda_unpaired=0.5)
             for r in rows if r["method"] == "asp"]
    res = compute(pd.DataFrame(rows), cfg())
    out = tmp_path_factory.mktemp("latex")
    return res, write_latex_tables(res, out)


def test_latex_tables_are_well_formed_booktabs_tabulars(latex_result):
    from asp_dist.analysis.latex_tables import LATEX_TABLES

    res, written = latex_result
    assert set(written) == set(LATEX_TABLES)
    for name, path in written.items():
        tex = path.read_text()
        assert tex.isascii(), name  # every sign spelled as LaTeX: pdflatex needs no inputenc for it
        assert _braces_balance(tex), name
        assert [tex.count(r) for r in (r"\toprule", r"\bottomrule")] == [1, 1] and r"\midrule" in tex, name
        assert tex.index(r"\toprule") < tex.index(r"\midrule") < tex.index(r"\bottomrule"), name
        spec, rows = _tex_rows(tex)
        assert len(rows) >= 2 and all(len(r) == len(spec) for r in rows), (name, spec, rows[:2])
        body = "\n".join(line for line in tex.splitlines() if not line.startswith("%"))
        assert not re.search(r"(?<!\\)[_%#]", re.sub(r"\$[^$]*\$", "", body)), name  # specials escaped
    summary = written["summary"].read_text()
    assert r"signaling\_skew=1.5" in summary and r"ASP[lambda\_unpaired=0.5]" in summary


def test_latex_tables_bold_the_best_value_of_each_row_in_the_metrics_direction(latex_result):
    from asp_dist.analysis.latex_tables import label

    res, written = latex_result
    spec, rows = _tex_rows(written["summary"].read_text())
    header, data = [h.strip() for h in rows[0]], rows[1:]
    asp = header.index(r"ASP[lambda\_unpaired=1]")
    # lower is better here and ASP has the lowest error by construction: its median is bold in every row,
    # and so is its twin ASP[lambda_unpaired=0.5] (the same rows): a tie after rounding is bold twice
    assert all(r"\textbf" in row[asp] and r"\textbf" in row[asp - 1] for row in data)
    assert all(sum(r"\textbf" in c for c in row) == 2 for row in data)
    _, rows = _tex_rows(written["iqm"].read_text())
    iqm = res.tables["iqm"]
    for row, (_, g) in zip(rows[1:], iqm.groupby(["domain", "condition", "paired"], sort=False)):
        best = g.loc[g["iqm_norm"].idxmax(), "treatment"]  # the largest normalised IQM, whatever the metric
        assert r"\textbf" in row[header.index(label(best))], (row, best)


@pytest.mark.skipif(shutil.which("pdflatex") is None,
                    reason="no pdflatex (Debian: apt-get install texlive-latex-base texlive-latex-recommended)")
def test_latex_tables_compile_in_a_minimal_document(latex_result, tmp_path):
    _, written = latex_result
    inputs = "\n\\bigskip\n".join(f"\\input{{{p.as_posix()}}}" for p in written.values())
    (tmp_path / "doc.tex").write_text("\\documentclass{article}\n\\usepackage{booktabs}\n\\begin{document}\n"
                                      f"{inputs}\n\\end{{document}}\n")
    proc = subprocess.run(["pdflatex", "-interaction=nonstopmode", "-halt-on-error", "doc.tex"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:]
    assert (tmp_path / "doc.pdf").stat().st_size > 1000


def test_latex_escapes_and_numbers():
    from asp_dist.analysis.latex_tables import escape, number

    assert escape("a_b & 5% #1 {x} ~^ $ \\") == (r"a\_b \& 5\% \#1 \{x\} \textasciitilde{}\textasciicircum{} \$ "
                                                 r"\textbackslash{}")
    assert escape("Δ − ½ –") == r"$\Delta$ $-$ $\frac{1}{2}$ --"
    assert number("-0.118") == "$-$0.118" and number("5.230e-16") == r"$5.230\times10^{-16}$"
    assert number("-1.5e+05") == r"$-1.5\times10^{5}$" and number("–") == "--" and number("abc_d") == r"abc\_d"
    assert number("-0") == "0" and number("-0.0") == "0.0"


def test_stats_job_writes_report_md_html_and_latex_by_default(tmp_path):
    from asp_dist.analysis.latex_tables import LATEX_TABLES
    from asp_dist.commands.stats import run_stats_job

    sweep = write_sweep(tmp_path / "all", make_rows(trials=range(4)))
    report = run_stats_job([str(sweep)], cfg=cfg(), log=lambda m: None)
    assert report == sweep / "report.md"
    html = (sweep / "report.html").read_text()
    assert html.startswith("<!DOCTYPE html>") and "ASP beat PC and OSP" in html and "<svg" in html
    figures = sorted((sweep / "figures").glob("*.svg"))
    assert html.count('<figure class="plot"') == len(figures) > 0
    assert f"{len(figures)} figures, each also as PNG and SVG" in report.read_text()
    for name in LATEX_TABLES:
        assert (sweep / "stats" / f"{name}.tex").read_text().startswith("% asp-dist stats")
    assert "also as booktabs LaTeX" in report.read_text()


def test_formats_choose_the_outputs(tmp_path):
    from asp_dist.cli import main

    sweep = write_sweep(tmp_path / "f", make_rows(trials=range(3)))
    assert main(["stats", str(sweep), "--quiet", "--no-figures", "--bootstrap", "200", "--formats", "html"]) == 0
    assert (sweep / "report.html").exists() and not (sweep / "report.md").exists()
    assert not list((sweep / "stats").glob("*.tex")) and (sweep / "stats" / "summary.parquet").exists()
    html = (sweep / "report.html").read_text()
    assert "No figures" in html and "<svg" not in html and "also as booktabs LaTeX" not in html
    out = tmp_path / "latex-only"
    assert main(["stats", str(sweep), "--out", str(out), "--quiet", "--no-figures", "--bootstrap", "200",
                 "--formats", "LaTeX, md"]) == 0
    assert (out / "report.md").exists() and (out / "stats" / "summary.tex").exists()
    assert not (out / "report.html").exists()
