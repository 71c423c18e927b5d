"""The rliable view (asp_dist/analysis/rliable_view.py) against the rliable package, and in the stats job.

Two references:

- `rliable.metrics` (numpy and scipy only, imports everywhere): the IQM and the probability of
  improvement, on the data and on every resample of a *fixed* stratified index set. Same indices, so
  the bootstrap distributions must agree exactly, and the intervals too (arch's "percentile" method,
  which rliable uses, is numpy's linear percentile).
- `rliable.library` (needs `arch` < 8, which does not import under pandas >= 3): rliable's own
  stratified bootstrap with its own random draws. Its interval ends are compared with ours within
  4 Monte Carlo standard errors of the difference of two independent percentile estimates:
  SE of one 2.5 % quantile from B resamples ≈ sqrt(p (1 − p) / B) / f(q), with f the density of the
  bootstrap distribution at q, ≈ φ(1.96) / σ for a near-normal one (σ its sd), so the tolerance is
  4 · sqrt(2) · sqrt(0.025 · 0.975 / B) · σ / φ(1.96) ≈ 0.21 σ at B = 5,000, plus one lattice step
  where the statistic is discrete (P(A > B) moves in steps of 1 / (n_A n_B)).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps
from test_stats import make_rows

from asp_dist.analysis import rliable_view as rv
from asp_dist.analysis.job import compute
from asp_dist.analysis.tables import StatsConfig

rliable_metrics = pytest.importorskip("rliable.metrics")


def rliable_library():
    """rliable.library, imported under pandas 3 too. It imports arch 7, which calls pandas' private
    `deprecate_kwarg` with its pandas 2 signature (old_arg_name, new_arg_name) where pandas 3 wants the warning
    class first; for that one import the helper takes the old call (FutureWarning, as pandas 2 used), then is
    put back. rliable's own code runs unchanged. A skip, saying why, only if it still cannot be imported."""
    import pandas.util._decorators as decorators

    original = decorators.deprecate_kwarg

    def pandas2_signature(*args, **kwargs):
        if args and isinstance(args[0], str):
            args = (FutureWarning, *args)
        return original(*args, **kwargs)

    decorators.deprecate_kwarg = pandas2_signature
    try:
        from rliable import library
    except Exception as err:
        pytest.skip(f"rliable.library does not import here ({type(err).__name__}: {err})")
    finally:
        decorators.deprecate_kwarg = original
    return library


def scores(runs: int = 20, tasks: int = 3, seed: int = 0, decimals: int | None = None) -> np.ndarray:
    """A (runs × tasks) matrix, rliable's layout; rounded to produce ties when asked."""
    x = np.random.default_rng(seed).normal(size=(runs, tasks)) + np.arange(tasks)
    return np.round(x, decimals) if decimals is not None else x


def columns(matrix: np.ndarray) -> list[np.ndarray]:
    return [matrix[:, t] for t in range(matrix.shape[1])]


def cfg(**kw) -> StatsConfig:
    return StatsConfig(n_boot=400, **kw)


# ---- against rliable.metrics, on the same resamples ---------------------------------------------------

def test_iqm_equals_rliable_on_data_and_on_every_resample():
    x = scores(runs=18, tasks=3)
    assert rv.iqm(x, axis=None) == pytest.approx(rliable_metrics.aggregate_iqm(x))
    assert rv.iqm(x[:, 0], axis=None) == pytest.approx(sps.trim_mean(x[:, 0], 0.25))
    indices = rv.stratified_indices([18, 18, 18], 200, np.random.default_rng(1))
    ours = rv.iqm_distribution(columns(x), indices)
    theirs = [rliable_metrics.aggregate_iqm(np.stack([x[idx[b], t] for t, idx in enumerate(indices)], axis=1))
              for b in range(200)]
    np.testing.assert_allclose(ours, theirs, rtol=1e-12)
    lo, hi = rv.percentile_interval(ours, 0.95)
    assert (lo, hi) == pytest.approx(tuple(np.percentile(theirs, [2.5, 97.5])))


def test_probability_of_improvement_equals_rliable_with_ties_and_unequal_runs():
    x, y = scores(runs=12, tasks=3, seed=2, decimals=0), scores(runs=9, tasks=3, seed=3, decimals=0) + 0.3
    tasks = list(zip(columns(x), columns(y)))
    assert rv.poi_unpaired(tasks) == pytest.approx(rliable_metrics.probability_of_improvement(x, y))
    assert rv.poi_unpaired([(x[:, 0], x[:, 0])]) == 0.5  # identical runs: rliable's special case
    rng = np.random.default_rng(4)
    ia, ib = rv.stratified_indices([12] * 3, 100, rng), rv.stratified_indices([9] * 3, 100, rng)
    ours = rv.poi_unpaired_distribution(tasks, ia, ib)
    theirs = [rliable_metrics.probability_of_improvement(
        np.stack([x[a[b], t] for t, a in enumerate(ia)], axis=1),
        np.stack([y[c[b], t] for t, c in enumerate(ib)], axis=1)) for b in range(100)]
    np.testing.assert_allclose(ours, theirs, rtol=1e-12)


def test_paired_probability_counts_ties_as_half_and_resamples_blocks():
    a, b = np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.0, 2.0, 5.0, 1.0])
    wins = rv.block_wins(a, b)
    assert list(wins) == [1.0, 0.5, 0.0, 1.0] and rv.poi_paired([wins]) == pytest.approx(0.625)
    assert rv.poi_paired([wins, np.ones(2)]) == pytest.approx((0.625 + 1.0) / 2)  # the mean over tasks
    idx = [np.array([[0, 0, 0, 0], [2, 2, 1, 1]])]
    assert list(rv.poi_paired_distribution([wins], idx)) == [1.0, 0.25]


def test_profile_is_the_fraction_of_runs_above_tau_on_every_resample():
    x = scores(runs=15, tasks=2, seed=5)
    taus = np.linspace(-1, 3, 9)
    # rliable's run_score_deviation: np.mean(scores > tau) over runs and tasks.
    assert list(rv.profile(x.ravel(), taus)) == [np.mean(x > t) for t in taus]
    indices = rv.stratified_indices([15, 15], 50, np.random.default_rng(6))
    ours = rv.profile_distribution(columns(x), indices, taus)
    for b in range(50):
        resample = np.stack([x[idx[b], t] for t, idx in enumerate(indices)], axis=1)
        np.testing.assert_allclose(ours[b], [np.mean(resample > t) for t in taus])


def test_draw_counts_match_the_indices():
    idx = np.array([[0, 0, 2], [1, 2, 2]])
    assert rv.draw_counts(idx, 4).tolist() == [[2, 0, 1, 0], [0, 1, 2, 0]]


# ---- against rliable's own bootstrap (where rliable.library imports) ----------------------------------------

def tolerance(dist: np.ndarray, reps: int, step: float = 0.0) -> float:
    se = np.sqrt(0.025 * 0.975 / reps) * np.std(dist) / sps.norm.pdf(1.96)
    return 4 * np.sqrt(2) * se + step


def test_intervals_match_rliables_own_stratified_bootstrap():
    library = rliable_library()
    reps = 5000
    x = scores(runs=20, tasks=3, seed=7)
    np.random.seed(0)  # rliable draws from numpy's global generator
    _, theirs = library.get_interval_estimates({"x": x}, lambda s: np.array([rliable_metrics.aggregate_iqm(s)]),
                                               reps=reps)
    point, lo, hi = rv.bootstrap_iqm(columns(x), reps, 0.95, seed=1)
    dist = rv.iqm_distribution(columns(x), rv.stratified_indices([20] * 3, reps, np.random.default_rng(1)))
    tol = tolerance(dist, reps)
    assert lo == pytest.approx(theirs["x"][0, 0], abs=tol) and hi == pytest.approx(theirs["x"][1, 0], abs=tol)

    y = scores(runs=20, tasks=3, seed=8) + 0.4
    reps = 2000
    np.random.seed(0)
    _, theirs = library.get_interval_estimates(
        {"xy": [x, y]}, lambda a, b: np.array([rliable_metrics.probability_of_improvement(a, b)]), reps=reps)
    tasks = list(zip(columns(x), columns(y)))
    _, lo, hi = rv.bootstrap_poi_unpaired(tasks, reps, 0.95, seed=2)
    rng = np.random.default_rng(2)
    dist = rv.poi_unpaired_distribution(tasks, rv.stratified_indices([20] * 3, reps, rng),
                                        rv.stratified_indices([20] * 3, reps, rng))
    tol = tolerance(dist, reps, step=1 / 400)
    assert lo == pytest.approx(theirs["xy"][0, 0], abs=tol) and hi == pytest.approx(theirs["xy"][1, 0], abs=tol)


def test_profiles_match_rliables_create_performance_profile():
    library = rliable_library()
    reps = 2000
    x = scores(runs=20, tasks=3, seed=9)
    taus = np.linspace(-1, 3, 9)
    np.random.seed(0)
    theirs, bands = library.create_performance_profile({"x": x}, taus, reps=reps)
    frac, lo, hi = rv.bootstrap_profile(columns(x), taus, reps, 0.95, seed=3)
    np.testing.assert_allclose(frac, theirs["x"])
    step = 1 / x.size  # a profile moves in steps of one run out of all of them
    sd = np.sqrt(frac * (1 - frac) / x.size)  # the bootstrap sd of a fraction, near enough
    tol = 4 * np.sqrt(2) * np.sqrt(0.025 * 0.975 / reps) * sd / sps.norm.pdf(1.96) + step
    np.testing.assert_array_less(np.abs(lo - bands["x"][0]), tol + 1e-12)
    np.testing.assert_array_less(np.abs(hi - bands["x"][1]), tol + 1e-12)


# ---- in the stats job --------------------------------------------------------------------------------------

def test_normalised_score_is_anchored_at_pc_with_least_data_and_the_base_self_play():
    rows = pd.DataFrame(make_rows(paired=(0, 1, 2, 4)))
    res = compute(rows, cfg())
    norm = res.tables["normalisation"].iloc[0]
    pc0 = rows[(rows.method == "pc") & (rows.paired == 0)]["eval_mixed"].median()
    assert norm["zero"] == pytest.approx(pc0) and "PC at 0 paired" in norm["zero_rule"]
    assert norm["one"] == pytest.approx(3.0) and "eval_self_play_base" in norm["one_rule"]
    iqm = res.tables["iqm"]
    np.testing.assert_allclose(iqm["iqm_norm"], (iqm["iqm"] - pc0) / (3.0 - pc0))
    assert (iqm["norm_ci_low"] <= iqm["iqm_norm"]).all() and (iqm["iqm_norm"] <= iqm["norm_ci_high"]).all()
    # Without a 0-paired count, zero is PC's median at the smallest count.
    res = compute(rows[rows.paired > 0], cfg())
    assert "PC at 1 paired" in res.tables["normalisation"].iloc[0]["zero_rule"]


def test_rliable_tables_do_not_depend_on_the_metric_direction():
    out = {}
    for higher in (True, False):
        rows = pd.DataFrame(make_rows(domain="levers", paired=(1, 2, 4, 8), higher=higher))
        rows["eval_self_play_base"] = 3.0 if higher else -3.0  # the same outcomes, stored negated
        out[higher] = compute(rows, cfg()).tables
    cols = ["iqm_norm", "norm_ci_low", "norm_ci_high"]
    pd.testing.assert_frame_equal(out[True]["iqm"][cols], out[False]["iqm"][cols])
    np.testing.assert_allclose(out[True]["iqm"]["iqm"], -out[False]["iqm"]["iqm"])
    np.testing.assert_allclose(out[True]["iqm"]["ci_low"], -out[False]["iqm"]["ci_high"])
    imp = ["poi", "poi_ci_low", "poi_ci_high", "poi_paired", "poi_paired_ci_low", "poi_paired_ci_high"]
    pd.testing.assert_frame_equal(out[True]["improvement"][imp], out[False]["improvement"][imp])
    pd.testing.assert_frame_equal(out[True]["aggregate"], out[False]["aggregate"])


def test_clear_effect_gives_improvement_above_half_and_agrees_with_friedman():
    res = compute(pd.DataFrame(make_rows(paired=(0, 1, 2, 4), trials=range(10))), cfg())
    imp = res.tables["improvement"].set_index(["a", "b"])
    assert imp.loc[("asp", "pc"), "poi_paired_ci_low"] > 0.5 and imp.loc[("asp", "pc"), "poi_ci_low"] > 0.5
    assert imp.loc[("asp", "pc"), "n_tasks"] == 4 and imp.loc[("asp", "pc"), "n_blocks"] == 40
    agree = res.tables["rliable_agreement"].set_index(["a", "b"])
    assert agree.loc[("asp", "pc"), "rliable_paired"] == "asp better"
    assert agree.loc[("asp", "pc"), "rank_call"] == "asp better" and agree.loc[("asp", "pc"), "agree_paired"]
    agg = res.tables["aggregate"].set_index("treatment")
    assert agg.loc["asp", "ci_low"] > agg.loc["pc", "ci_high"]
    per = res.tables["improvement_by_paired"]
    assert set(per["paired"]) == {0, 1, 2, 4} and (per["n_blocks"] == 10).all()


def test_identical_methods_leave_half_inside_every_interval():
    same = {"pc": 0.0, "osp": 0.0, "asp": 0.0}
    res = compute(pd.DataFrame(make_rows(effect=same, noise=0.0)), cfg())
    imp = res.tables["improvement"]
    assert (imp["poi"] == 0.5).all() and (imp["poi_paired"] == 0.5).all()
    agree = res.tables["rliable_agreement"]
    assert (agree["rliable_paired"] == "uncertain").all() and agree["agree_paired"].all()


def test_paired_range_bounds_the_pooled_tasks_and_profiles_span_zero_to_one():
    rows = pd.DataFrame(make_rows(domain="particles", paired=range(0, 7), trials=range(4)))
    res = compute(rows, cfg())
    imp = res.tables["improvement"]
    assert (imp["paired_range"] == "2-4").all() and (imp["n_tasks"] == 3).all()
    prof = res.tables["profiles"]
    assert prof["tau"].min() <= 0 and prof["tau"].max() >= 1
    assert (prof["ci_low"] <= prof["fraction"] + 1e-12).all() and (prof["fraction"] <= prof["ci_high"] + 1e-12).all()
    # A profile never rises with τ.
    for _, g in prof.groupby(["scope", "treatment"]):
        assert (np.diff(g["fraction"].to_numpy()) <= 1e-12).all()


def test_a_groups_interval_does_not_depend_on_other_groups():
    rows = pd.DataFrame(make_rows(trials=range(6)))
    full = compute(rows, cfg()).tables["iqm"]
    alone = compute(rows[rows.method.isin(["pc", "asp"])], cfg()).tables["iqm"]
    a = full[full.treatment == "asp"].set_index("paired")[["iqm", "ci_low", "ci_high"]]
    b = alone[alone.treatment == "asp"].set_index("paired")[["iqm", "ci_low", "ci_high"]]
    pd.testing.assert_frame_equal(a, b)


def test_aggregate_pools_domains_with_their_own_anchors():
    rows = pd.DataFrame(make_rows(trials=range(5)) + make_rows(domain="vae", paired=(8, 16, 32), trials=range(5),
                                                               higher=False, knobs={"vae_latent_dim": [2, 32]}))
    res = compute(rows, cfg())
    assert len(res.tables["normalisation"]) == 3  # signaling, and vae at each latent size
    agg = res.tables["aggregate"]
    assert list(dict.fromkeys(agg["scope"])) == ["all domains", "signaling", "vae"]
    every = agg[agg["scope"] == "all domains"].set_index("treatment")
    assert every.loc["asp", "n_tasks"] == 4 + 2 * 3 and every.loc["asp", "n_runs"] == 5 * 10


def test_tables_report_and_figures_are_written(tmp_path):
    from asp_dist.analysis.job import write_tables
    from asp_dist.analysis.report import write_report
    from asp_dist.analysis.rliable_plots import plot_rliable

    res = compute(pd.DataFrame(make_rows(trials=range(4))), cfg())
    written = write_tables(res, tmp_path)
    for name in rv.TABLES:
        assert name in written and (tmp_path / "stats" / f"{name}.md").read_text().startswith("|")
    back = pd.read_parquet(written["improvement"])
    assert len(back) == len(res.tables["improvement"]) == 3
    figures = plot_rliable(res, tmp_path / "figures")
    assert {f.name for f in figures} == {"signaling_iqm_vs_paired", "rliable_aggregate", "rliable_profiles",
                                         "rliable_improvement"}
    assert all(p.exists() for f in figures for p in f.paths)
    text = write_report(res, tmp_path, figures).read_text()
    section = text[text.index("## The rliable view"):text.index("## What was run")]
    assert "P(ASP > PC)" in section and "agree on" in section and "IQM of the normalised score" in section
