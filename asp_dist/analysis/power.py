"""How many trials a comparison needs: the power of the paper's test (or Wilcoxon–Holm) for one comparison of
a sweep's rows, estimated by resampling whole trials, and the trial count that reaches a target power.

A *comparison* is two treatments (``a`` better than ``b``: ASP over OSP, say) of one domain and condition over a
paired range, judged among a set of treatments (default: every treatment in range, as the stats job does):

    friedman-nemenyi   the paper's: Friedman over the treatments (blocks = trial x paired count) at alpha,
                       then Nemenyi's post-hoc p(a, b) < alpha, with a's mean rank better than b's
    wilcoxon-holm      the second view: Wilcoxon signed-rank of a - b over the same blocks, Holm-adjusted over
                       every pair of the treatments, < alpha, with a's median difference > 0 (and, with three
                       or more treatments, Friedman at alpha first, as the stats job requires)

Power at n trials = how often the test rejects on n trials drawn with replacement from the sweep's trials, each
with all its paired counts (a trial is the unit the sweep adds: its blocks share a base and data seeds). This
is the calibration study's rule (asp_dist.analysis.calibration.power: Friedman with ASP best) made general.
The estimate is only as good as the rows it resamples: with few trials it inherits their sampling error, and
it is checked in tests/test_power.py against simulations of a known effect.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pandas as pd

from asp_dist.analysis.layout import domain_layout, label_rows, treatment_order
from asp_dist.analysis.rank_tests import (friedman, friedman_each, holm, holm_each, mean_ranks, mean_ranks_each,
                                            wilcoxon, wilcoxon_each)
from asp_dist.analysis.tables import block_matrix
from asp_dist.errors import SpecError

TESTS = ("friedman-nemenyi", "wilcoxon-holm")
SIZES = (5, 10, 15, 20, 25, 30, 40, 50, 60, 80, 100, 120, 150, 200, 300)


@dataclass
class Comparison:
    """One comparison's complete blocks (index root_seed, trial, paired; one column per treatment, scores:
    larger is better) and what is compared."""

    domain: str
    condition: str
    paired: tuple[int, int]
    a: str
    b: str
    blocks: pd.DataFrame

    @property
    def trials(self) -> list[int]:
        return sorted(self.blocks.index.get_level_values("trial").unique())


@dataclass
class PowerEstimate:
    comparison: Comparison
    test: str
    alpha: float
    target: float
    rates: dict[int, float] = field(default_factory=dict)  # trials -> estimated power
    observed_rejects: bool = False  # the test on the sweep's own trials

    @property
    def current(self) -> int:
        return len(self.comparison.trials)

    @property
    def needed(self) -> int | None:
        """The smallest trial count whose estimated power reaches the target (None: none of SIZES does)."""
        return next((n for n in sorted(self.rates) if self.rates[n] >= self.target), None)


def comparison(rows: pd.DataFrame, domain: str, a: str, b: str, paired: tuple[int, int] | None = None,
               condition: str | None = None, treatments: Sequence[str] | None = None,
               metric: str = "eval_mixed") -> Comparison:
    """The blocks of `a` against `b` among `treatments` (default: all in range) for one condition."""
    rows = rows[rows["domain"] == domain]
    if rows.empty:
        raise SpecError(f"no {domain} rows")
    layout = domain_layout(rows, metric)
    rows = label_rows(rows, layout, metric)
    conditions = sorted(rows["condition"].unique())
    if condition is None:
        if len(conditions) > 1:
            raise SpecError(f"{domain} rows hold {len(conditions)} conditions ({', '.join(conditions)}); "
                            f"choose one with --condition")
        condition = conditions[0]
    if condition not in conditions:
        raise SpecError(f"no {domain} condition {condition!r}; the rows have {', '.join(conditions)}")
    rows = rows[rows["condition"] == condition]
    lo, hi = paired if paired is not None else (int(rows["paired"].min()), int(rows["paired"].max()))
    rows = rows[(rows["paired"] >= lo) & (rows["paired"] <= hi)]
    present = treatment_order(rows["treatment"])
    chosen = list(treatments) if treatments else present
    for t in {a, b, *chosen}:
        if t not in present:
            raise SpecError(f"no {domain} rows of treatment {t!r} at paired {lo}-{hi} ({condition}); "
                            f"there are {', '.join(present) or 'none'}")
    if a == b:
        raise SpecError(f"compare two different treatments, got {a!r} twice")
    chosen = treatment_order(set(chosen) | {a, b})
    blocks = block_matrix(rows, chosen)
    if blocks.index.get_level_values("trial").nunique() < 2:
        raise SpecError(f"{domain} ({condition}) has complete blocks of fewer than two trials at paired {lo}-{hi}")
    return Comparison(domain, condition, (lo, hi), a, b, blocks)


def nemenyi_pair(scores: np.ndarray, i: int, j: int) -> float:
    """Nemenyi's p for treatments i and j after Friedman (rank_tests.nemenyi's, for one pair: what the
    resampling loop needs thousands of times)."""
    from scipy.stats import studentized_range

    n, k = scores.shape
    ranks = mean_ranks(scores)
    q = abs(ranks[i] - ranks[j]) / np.sqrt(k * (k + 1) / (6.0 * n)) * np.sqrt(2.0)
    return float(studentized_range.sf(q, k, np.inf)) if q > 0 else 1.0


def rejects(scores: np.ndarray, ia: int, ib: int, test: str, alpha: float) -> bool:
    """Whether `test` finds treatment ia better than ib on these blocks x treatments scores."""
    k = scores.shape[1]
    if k >= 3:
        _, p = friedman(scores)
        if not p < alpha:
            return False
    if test == "friedman-nemenyi":
        if k < 3:
            raise SpecError("friedman-nemenyi needs three or more treatments; use --test wilcoxon-holm")
        ranks = mean_ranks(scores)
        return bool(nemenyi_pair(scores, ia, ib) < alpha and ranks[ia] < ranks[ib])
    pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
    ps = holm([wilcoxon(scores[:, i] - scores[:, j])[1] for i, j in pairs])
    p = ps[pairs.index((min(ia, ib), max(ia, ib)))]
    return bool(p < alpha and np.median(scores[:, ia] - scores[:, ib]) > 0)


def rejects_each(scores: np.ndarray, ia: int, ib: int, test: str, alpha: float) -> np.ndarray:
    """`rejects` of each samples x blocks x treatments sample at once (equal to it sample by sample:
    tests/test_power.py)."""
    _, n, k = scores.shape
    found = np.ones(len(scores), dtype=bool)
    if k >= 3:
        found &= friedman_each(scores) < alpha
    if test == "friedman-nemenyi":
        if k < 3:
            raise SpecError("friedman-nemenyi needs three or more treatments; use --test wilcoxon-holm")
        from scipy.stats import studentized_range

        ranks = mean_ranks_each(scores)
        found &= ranks[:, ia] < ranks[:, ib]
        q = abs(ranks[:, ia] - ranks[:, ib]) / np.sqrt(k * (k + 1) / (6.0 * n)) * np.sqrt(2.0)  # nemenyi_pair's
        candidates = np.flatnonzero(found)  # Nemenyi's p (an integral each) only where it decides
        found[candidates] = studentized_range.sf(q[candidates], k, np.inf) < alpha
        return found
    found &= np.median(scores[:, :, ia] - scores[:, :, ib], axis=1) > 0
    left = scores[found]  # Wilcoxon only where it decides (a small sample's is a permutation test)
    pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
    ps = holm_each(np.stack([wilcoxon_each(left[:, :, i] - left[:, :, j]) for i, j in pairs], axis=1))
    found[found] = ps[:, pairs.index((min(ia, ib), max(ia, ib)))] < alpha
    return found


def resampled(per_trial: Sequence[np.ndarray], picks: Sequence[np.ndarray], most: int = 1 << 22):
    """The samples x blocks x treatments scores of every pick of trials, in stacks of at most `most` numbers;
    each stack holds picks of one block count (trials may differ in blocks)."""
    size = np.array([len(t) for t in per_trial])
    blocks = np.array([size[p].sum() for p in picks])
    for count in np.unique(blocks):
        same = np.flatnonzero(blocks == count)
        step = max(1, most // max(1, count * per_trial[0].shape[1]))
        for start in range(0, len(same), step):
            yield np.stack([np.concatenate([per_trial[i] for i in picks[j]]) for j in same[start:start + step]])


def estimate(comp: Comparison, test: str = "friedman-nemenyi", alpha: float = 0.05, target: float = 0.8,
             sizes: Sequence[int] = SIZES, resamples: int = 1000, seed: int = 0) -> PowerEstimate:
    """Power of `test` at every trial count in `sizes` (and at the sweep's own count), resampling trials."""
    if test not in TESTS:
        raise SpecError(f"unknown test {test!r}; choose one of {', '.join(TESTS)}")
    if not 0 < target < 1:
        raise SpecError(f"--target must be between 0 and 1, got {target}")
    cols = list(comp.blocks.columns)
    ia, ib = cols.index(comp.a), cols.index(comp.b)
    per_trial = [comp.blocks.xs(t, level="trial").to_numpy() for t in comp.trials]
    out = PowerEstimate(comp, test, alpha, target,
                        observed_rejects=rejects(np.concatenate(per_trial), ia, ib, test, alpha))
    rng = np.random.default_rng(seed)
    for n in sorted(set(sizes) | {len(per_trial)}):
        picks = [rng.integers(len(per_trial), size=n) for _ in range(resamples)]  # one draw per resample, as ever
        hits = sum(int(rejects_each(scores, ia, ib, test, alpha).sum()) for scores in resampled(per_trial, picks))
        out.rates[n] = hits / resamples
    return out


def trial_range(first: int, count: int) -> str:
    """The axis to add, as a space file writes it."""
    return f"trial = {{ first = {first}, last = {first + count - 1} }}"


def report(est: PowerEstimate, fresh_from: int | None = None) -> str:
    """The estimate as text: power by trial count, the count for the target, and the trials to add."""
    c = est.comparison
    lines = [f"{c.domain} ({c.condition}), paired {c.paired[0]}-{c.paired[1]}: {c.a} better than {c.b} "
             f"among {', '.join(c.blocks.columns)}; test {est.test} at alpha {est.alpha}",
             f"{est.current} trials ({len(c.blocks)} complete blocks) in the sweep; the test "
             f"{'rejects' if est.observed_rejects else 'does not reject'} on them",
             "", "| trials | estimated power |", "|---:|---:|"]
    lines += [f"| {n}{' (the sweep)' if n == est.current else ''} | {r:.3f} |" for n, r in sorted(est.rates.items())]
    need = est.needed
    lines.append("")
    if need is None:
        lines.append(f"power {est.target} is not reached by {max(est.rates)} trials")
        return "\n".join(lines)
    lines.append(f"trials for power {est.target}: {need}")
    if need > est.current:
        last = max(c.trials)
        lines.append(f"to grow this sweep to {need} trials (asp-dist sweep SPACE --name NAME --extend), add "
                     f"{need - est.current}: {trial_range(last + 1, need - est.current)}")
    if fresh_from is not None:
        lines.append(f"a replication on fresh trials: {trial_range(fresh_from, need)}")
    return "\n".join(lines)
