"""`asp-dist power`'s estimate (asp_dist.analysis.power) against simulations with a known effect: rows drawn
from a model where ASP beats OSP by a fixed margin; the power estimated by resampling one large sample's trials
must match the rate at which the test rejects on fresh samples from the model itself."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from asp_dist.analysis import power, rank_tests
from asp_dist.analysis.rank_tests import nemenyi
from asp_dist.cli import main
from asp_dist.errors import SpecError

PAIRED = (2, 3, 4)
EFFECT = {"pc": -0.3, "osp": 0.0, "asp": 0.25}  # mean score by method, in units of the within-block noise


def simulated_scores(trials: int, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """(trials x paired counts) blocks x (pc, osp, asp) scores: a trial effect and a paired effect shared by a
    block's methods, the method's effect, and independent noise of sd 1."""
    trial = np.repeat(rng.normal(0, 0.5, size=trials), len(PAIRED))[:, None]
    paired = np.tile(0.2 * np.array(PAIRED, dtype=float), trials)[:, None]
    effect = scale * np.array([EFFECT[m] for m in ("pc", "osp", "asp")])[None, :]
    return 10 + trial + paired + effect + rng.normal(size=(trials * len(PAIRED), 3))


def simulated_rows(trials: range, seed: int, scale: float = 1.0) -> pd.DataFrame:
    scores = simulated_scores(len(trials), np.random.default_rng(seed), scale)
    keys = [(t, p) for t in trials for p in PAIRED]
    return pd.DataFrame([{"domain": "signaling", "method": m, "paired": p, "trial": t, "root_seed": 0,
                          "eval_mixed": scores[b, c], "eval_mixed_higher_is_better": True}
                         for b, (t, p) in enumerate(keys) for c, m in enumerate(("pc", "osp", "asp"))])


def true_power(n: int, test: str, draws: int = 400) -> float:
    """How often the test rejects on fresh n-trial samples from the model (columns pc, osp, asp)."""
    rng = np.random.default_rng(10_000 + n)
    fresh = np.stack([simulated_scores(n, rng) for _ in range(draws)])
    return power.rejects_each(fresh, 2, 1, test, 0.05).sum() / draws  # = rejects of each (tested below)


@pytest.mark.parametrize("test", power.TESTS)
def test_the_estimate_matches_the_power_of_fresh_samples(test):
    sample = power.comparison(simulated_rows(range(200), seed=1), "signaling", "asp", "osp")
    est = power.estimate(sample, test, sizes=(10, 30), resamples=400, seed=2)
    for n in (10, 30):
        truth = true_power(n, test)
        # Monte Carlo error of each side is about 0.025; the sample's own error (200 trials) about as much.
        assert est.rates[n] == pytest.approx(truth, abs=0.1), (n, est.rates[n], truth)
    assert est.rates[10] < est.rates[30]  # power grows with trials


def coarse_rows(methods=("pc", "osp", "asp")) -> pd.DataFrame:
    """Rows whose scores tie often (one decimal), with a trial whose scores all tie and a trial that lost a
    block (trials of unequal block counts)."""
    rows = simulated_rows(range(12), seed=6)
    rows = rows[rows["method"].isin(methods)].copy()
    rows["eval_mixed"] = rows["eval_mixed"].round(0)
    rows.loc[rows["trial"] == 3, "eval_mixed"] = 10.0
    return rows.drop(rows.index[(rows["trial"] == 5) & (rows["paired"] == 4) & (rows["method"] == "asp")])


def one_by_one(comp: power.Comparison, test: str, sizes, resamples: int, seed: int) -> dict[int, float]:
    """The estimate's rates as its loop computed them before, one resample and one `rejects` at a time."""
    cols = list(comp.blocks.columns)
    ia, ib = cols.index(comp.a), cols.index(comp.b)
    per_trial = [comp.blocks.xs(t, level="trial").to_numpy() for t in comp.trials]
    rng, rates = np.random.default_rng(seed), {}
    for n in sorted(set(sizes) | {len(per_trial)}):
        hits = 0
        for _ in range(resamples):
            pick = rng.integers(len(per_trial), size=n)
            hits += power.rejects(np.concatenate([per_trial[i] for i in pick]), ia, ib, test, 0.05)
        rates[n] = hits / resamples
    return rates


@pytest.mark.parametrize("test,methods", [("friedman-nemenyi", ("pc", "osp", "asp")),
                                          ("wilcoxon-holm", ("pc", "osp", "asp")), ("wilcoxon-holm", ("osp", "asp"))])
def test_resamples_tested_at_once_give_what_the_one_by_one_loop_gave(test, methods):
    comp = power.comparison(coarse_rows(methods), "signaling", "asp", "osp")
    assert comp.blocks.groupby(level="trial").size().nunique() == 2  # blocks stacked by count
    est = power.estimate(comp, test, sizes=(6, 10, 20), resamples=200, seed=7)  # 14+ blocks: no permutation test
    assert est.rates == one_by_one(comp, test, (6, 10, 20), 200, 7)
    assert 0 < est.rates[20] < 1  # the rates decide something


@pytest.mark.parametrize("k", [2, 3, 4])
def test_each_sample_of_a_stack_is_tested_as_on_its_own(k):
    rng = np.random.default_rng(k)
    scores = rng.normal(size=(200, 16, k)).round(0) + np.linspace(0, 1.5, k)  # ties, zero differences
    scores[:5] = 2.0  # samples whose scores all tie
    scores[5:40] = rng.normal(size=(35, 16, k)) + np.linspace(0, 1.5, k)  # no ties: Wilcoxon's exact p
    for test in power.TESTS[k < 3:]:
        for alpha in (0.05, 0.5):
            at_once = power.rejects_each(scores, k - 1, 0, test, alpha)
            assert at_once.tolist() == [power.rejects(s, k - 1, 0, test, alpha) for s in scores]
            assert 0 < at_once.sum() < len(scores)
    pairs = np.stack([rank_tests.wilcoxon_each(scores[:, :, i] - scores[:, :, 0]) for i in range(1, k)], axis=1)
    pairs[0, 0] = np.nan
    assert np.array_equal(rank_tests.holm_each(pairs), np.stack([rank_tests.holm(p) for p in pairs]), equal_nan=True)


@pytest.mark.parametrize("n", [8, 30, 60])
def test_wilcoxon_of_each_row_is_scipys_for_that_row_alone(n):
    """scipy picks its method once per stack (exact, permutation, normal approximation); each row must get the
    p-value it gets alone, whatever the other rows hold."""
    rng = np.random.default_rng(n)
    rows = 12 if n < 13 else 200  # a permutation test each below 14
    d = rng.normal(0.3, 1, size=(rows, n))
    d[rows // 2:] = d[rows // 2:].round(0)  # ties and zeros in half of the rows
    d[0] = 0.0
    at_once = rank_tests.wilcoxon_each(d)
    assert at_once.tolist() == [rank_tests.wilcoxon(row)[1] for row in d]
    assert len(set(at_once.round(12))) > rows // 2


def test_the_trial_count_for_a_target_and_the_range_to_add():
    comp = power.comparison(simulated_rows(range(10), seed=3, scale=3.0), "signaling", "asp", "osp")
    est = power.estimate(comp, "wilcoxon-holm", sizes=(5, 10, 20, 40, 80, 160), resamples=200, seed=0)
    assert est.current == 10 and 10 in est.rates
    need = est.needed
    assert need is not None and est.rates[need] >= 0.8
    assert all(r < 0.8 for n, r in est.rates.items() if n < need)
    text = power.report(est, fresh_from=2000)
    assert f"trials for power 0.8: {need}" in text
    if need > 10:
        assert power.trial_range(10, need - 10) in text
    assert power.trial_range(2000, need) in text


def test_nemenyi_of_one_pair_equals_the_stats_jobs():
    scores = simulated_rows(range(12), seed=4).pivot_table(index=["trial", "paired"], columns="method",
                                                           values="eval_mixed")[["pc", "osp", "asp"]].to_numpy()
    full = nemenyi(scores)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        assert power.nemenyi_pair(scores, i, j) == pytest.approx(full[i, j], rel=1e-9, abs=1e-12)


def test_bad_comparisons_are_one_line(tmp_path):
    rows = simulated_rows(range(5), seed=5)
    with pytest.raises(SpecError, match="no signaling rows of treatment 'xsp'"):
        power.comparison(rows, "signaling", "xsp", "osp")
    with pytest.raises(SpecError, match="no levers rows"):
        power.comparison(rows, "levers", "asp", "osp")
    comp = power.comparison(rows, "signaling", "asp", "osp", treatments=["asp", "osp"])
    with pytest.raises(SpecError, match="needs three or more treatments"):
        power.estimate(comp, "friedman-nemenyi", resamples=10)


def test_power_command_on_a_sweep(capsys):
    assert main(["power", "results/examples/referential-small", "--domain", "referential", "--a", "asp",
                 "--b", "pc", "--paired", "1-8", "--resamples", "100", "--fresh-from", "2000"]) == 0
    out = capsys.readouterr().out
    assert "asp better than pc" in out and "| trials | estimated power |" in out
    assert main(["power", "results/examples/referential-small", "--domain", "referential", "--a", "asp",
                 "--b", "nsp"]) == 2
    assert capsys.readouterr().err.startswith("asp-dist: error: no referential rows of treatment 'nsp'")
