"""Small statistics on plain arrays (no rows, no pandas), each tested on a known answer.

Everything random is seeded by the caller; `group_seed` derives a group's seed from its key,
so a group's bootstrap interval does not depend on which other groups are present.
"""

from __future__ import annotations

import warnings
from typing import Any, Sequence

import numpy as np
from scipy import stats as sps

from asp_dist.hashing import stable_hash


def quartiles(values: Sequence[float]) -> tuple[float, float, float]:
    """(Q1, median, Q3) with linear interpolation between order statistics (numpy's default, type 7)."""
    q1, med, q3 = np.percentile(np.asarray(values, dtype=float), [25, 50, 75])
    return float(q1), float(med), float(q3)


def group_seed(seed: int, *key: Any) -> int:
    return int(stable_hash({"seed": seed, "key": [str(k) for k in key]})[:12], 16)


def bootstrap_median_ci(values: Sequence[float], n_boot: int = 2000, ci: float = 0.95,
                        seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the median; deterministic for a given seed."""
    x = np.asarray(values, dtype=float)
    if len(x) == 0:
        return float("nan"), float("nan")
    if len(x) == 1:
        return float(x[0]), float(x[0])
    rng = np.random.default_rng(seed)
    medians = np.median(x[rng.integers(0, len(x), size=(n_boot, len(x)))], axis=1)
    lo, hi = np.quantile(medians, [(1 - ci) / 2, 1 - (1 - ci) / 2])
    return float(lo), float(hi)


def holm(pvalues: Sequence[float]) -> np.ndarray:
    """Holm–Bonferroni adjusted p-values (NaNs are left out of the family and stay NaN)."""
    p = np.asarray(pvalues, dtype=float)
    out = np.full_like(p, np.nan)
    ok = np.flatnonzero(~np.isnan(p))
    if len(ok) == 0:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    m = len(order)
    adjusted = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[order]))
    out[order] = adjusted
    return out


def friedman(scores: np.ndarray) -> tuple[float, float]:
    """Friedman chi-square over a blocks x treatments array (tie-corrected); (0, 1) when all tie."""
    if scores.shape[1] < 3:
        raise ValueError("the Friedman test needs at least three treatments")
    if np.all(scores == scores[:, :1]):
        return 0.0, 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = sps.friedmanchisquare(*scores.T)
    return float(res.statistic), float(res.pvalue)


def mean_ranks(scores: np.ndarray) -> np.ndarray:
    """Mean rank of each treatment over blocks, 1 = best (largest score); ties share their mean rank."""
    return sps.rankdata(-scores, axis=1).mean(axis=0)


def wilcoxon(diffs: np.ndarray) -> tuple[float, float]:
    """Two-sided Wilcoxon signed-rank test of paired differences (zeros dropped); (0, 1) when all zero."""
    d = np.asarray(diffs, dtype=float)
    if len(d) == 0:
        return float("nan"), float("nan")
    if np.all(d == 0):
        return 0.0, 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = sps.wilcoxon(d, zero_method="wilcox", alternative="two-sided")
    return float(res.statistic), float(res.pvalue)


def nemenyi(scores: np.ndarray) -> np.ndarray:
    """Nemenyi post-hoc p-values (treatments x treatments) after Friedman, via scikit-posthocs."""
    import scikit_posthocs as sp

    if np.all(scores == scores[:, :1]):
        return np.ones((scores.shape[1], scores.shape[1]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.asarray(sp.posthoc_nemenyi_friedman(scores), dtype=float)


def spearman(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Spearman's rho and its two-sided p-value."""
    rho, p = sps.spearmanr(x, y)
    return float(rho), float(p)


# ---- the same tests on many samples at once (resampling: asp_dist.analysis.power, .calibration) -------------
# Each takes a stack of equally long samples (first axis: the sample) and gives what the one-sample function
# above gives for every sample, through scipy's own vectorized statistics: equal bit for bit
# (tests/test_power.py), 50-80 times faster than a Python loop over thousands of resamples.

def friedman_each(scores: np.ndarray) -> np.ndarray:
    """`friedman`'s p of each samples x blocks x treatments sample (1 where all its scores tie)."""
    if scores.shape[2] < 3:
        raise ValueError("the Friedman test needs at least three treatments")
    tied = np.all(scores == scores[:, :, :1], axis=(1, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p = sps.friedmanchisquare(*np.moveaxis(scores, 2, 0), axis=1).pvalue
    return np.where(tied, 1.0, p)


def mean_ranks_each(scores: np.ndarray) -> np.ndarray:
    """`mean_ranks` of each samples x blocks x treatments sample: samples x treatments."""
    return sps.rankdata(-scores, axis=2).mean(axis=1)


def wilcoxon_each(diffs: np.ndarray) -> np.ndarray:
    """`wilcoxon`'s p of each samples x differences row (1 where a row is all zero).

    scipy chooses its method ("auto") once for a whole stack: exact without ties or zeros up to 50
    differences, an exhaustive permutation test with them up to 13, else the normal approximation. Rows
    are therefore stacked by the method a row alone would get; permutation rows go one by one."""
    d = np.asarray(diffs, dtype=float)
    n = d.shape[1]
    p = np.ones(len(d))
    is_zero = d == 0
    zero = np.all(is_zero, axis=1)
    magnitudes = np.sort(np.abs(d), axis=1)
    plain = ~np.any(is_zero, axis=1) & ~np.any(magnitudes[:, 1:] == magnitudes[:, :-1], axis=1)  # no zeros, no ties
    groups = [(~zero, False)] if n > 50 else [(plain, False), (~plain & ~zero, n <= 13)]
    for rows, one_by_one in groups:
        if not rows.any():
            continue
        if one_by_one:
            p[rows] = [wilcoxon(row)[1] for row in d[rows]]
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            p[rows] = sps.wilcoxon(d[rows], zero_method="wilcox", alternative="two-sided", axis=1).pvalue
    return p


def holm_each(pvalues: np.ndarray) -> np.ndarray:
    """`holm` of each samples x family row (a row holding a NaN goes through `holm` itself)."""
    p = np.asarray(pvalues, dtype=float)
    m = p.shape[1]
    order = np.argsort(p, axis=1, kind="stable")
    scaled = (m - np.arange(m)) * np.take_along_axis(p, order, axis=1)
    out = np.empty_like(p)
    np.put_along_axis(out, order, np.minimum(1.0, np.maximum.accumulate(scaled, axis=1)), axis=1)
    for i in np.flatnonzero(np.isnan(p).any(axis=1)):
        out[i] = holm(p[i])
    return out
