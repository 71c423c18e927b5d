"""The rliable view of a sweep (Agarwal et al., NeurIPS 2021; the MARL protocol of Gorsane et al.,
NeurIPS 2022), beside the paper's rank tests. numpy and scipy only; tests/test_rliable_view.py checks
every statistic against the `rliable` package on the same data.

Words, all on the direction-corrected `score` of layout.py (larger is better):

- *run*: one cell, i.e. one trial of one treatment at one paired count of one condition.
- *task* (rliable's stratum): one (domain, condition, paired count).
- *block*: the runs of one task with the same (root_seed, trial): they share the base model, the
  paired and unpaired data and the initial weights.
- *normalised score*: (score − zero) / (one − zero), anchored per (domain, condition):
  zero = the median score of PC at 0 paired (at the condition's smallest paired count when it has
  no 0): what the paper's baseline reaches with the least paired data;
  one = the median, over the condition's rows, of the base pair's own self-play score
  (`eval_self_play_base`, same units and direction as the mixed metric): the base pair playing
  with itself, i.e. a new agent that adopted the base's convention perfectly. For a metric that is
  not a mixed-team score (not `eval_mixed*`), or rows without `eval_self_play_base`, one = the best
  (treatment, paired) median of the condition. The map is affine per condition, so ranks,
  P(A > B) and the rank tests do not change with it; it only puts conditions and domains on one scale.
- *IQM*: the interquartile mean of n pooled runs: sorted, ⌊n/4⌋ dropped at each end, the rest
  averaged (scipy.stats.trim_mean(x, 0.25), rliable's `aggregate_iqm`).
- *stratified bootstrap*: a resample draws, within every task independently, as many runs (with
  replacement) as the task has, and recomputes the statistic; the 95 % interval is the 2.5 % and
  97.5 % percentile of the resampled statistics (rliable's default, arch's "percentile" method).
- *P(A > B), unpaired* (rliable's probability of improvement): per task, P(X > Y) + ½ P(X = Y) for
  a random run X of A and Y of B (Mann–Whitney U / (n_A n_B)), averaged over tasks. Resampled: A's
  runs and B's runs independently within each task.
- *P(A > B), paired*: per task, the mean over its blocks of 1 (A's run scores higher), ½ (tie) or
  0, averaged over tasks. Resampled: blocks within each task. Both forms are reported per paired
  count and pooled over the paired range of the rank tests (the same resamples: a pooled resample
  is the mean of the counts' resamples, each count resampled independently).
- *performance profile*: the fraction of runs, pooled over tasks, whose normalised score is > τ,
  on a grid of τ, with a stratified-bootstrap band.

Every resample set is seeded from `--seed` and the key of what it estimates (rank_tests.group_seed),
so an interval does not depend on what else is in the sweep.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Sequence

import numpy as np
import pandas as pd

from asp_dist.analysis.layout import DomainLayout, by_condition, is_asp, treatment_order
from asp_dist.analysis.rank_tests import group_seed
from asp_dist.analysis.tables import StatsConfig, paired_range_for

TABLES = ("normalisation", "iqm", "aggregate", "improvement", "improvement_by_paired", "profiles",
          "rliable_agreement")
TAU_POINTS = 41  # points of the performance profiles' τ grid
TAU_LIMITS = (-1.0, 2.0)  # the grid spans [min(0, lowest), max(1, highest)] clipped to these


# ---- statistics on arrays ---------------------------------------------------------------------------

def iqm(values: np.ndarray, axis: int | None = -1) -> np.ndarray:
    """Interquartile mean: the mean of the values left after dropping ⌊n/4⌋ at each end of the sorted n
    (scipy.stats.trim_mean(values, 0.25, axis), computed with a sort: faster on many short rows)."""
    x = np.asarray(values, dtype=float)
    if axis is None:
        x, axis = x.ravel(), -1
    x = np.sort(np.moveaxis(x, axis, -1), axis=-1)
    cut = int(0.25 * x.shape[-1])
    return x[..., cut:x.shape[-1] - cut].mean(axis=-1)


def percentile_interval(dist: np.ndarray, ci: float) -> tuple[np.ndarray, np.ndarray]:
    """The (1 − ci)/2 and 1 − (1 − ci)/2 quantiles of resampled statistics (axis 0: the resamples)."""
    lo, hi = np.quantile(dist, [(1 - ci) / 2, 1 - (1 - ci) / 2], axis=0)
    return lo, hi


def stratified_indices(sizes: Sequence[int], n_boot: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Per task of n runs, an (n_boot, n) array: each resample draws n of its runs with replacement."""
    return [rng.integers(0, n, size=(n_boot, n)) for n in sizes]


def draw_counts(indices: np.ndarray, n: int) -> np.ndarray:
    """How often each of n runs is drawn in each resample: (n_boot, n) from (n_boot, k) indices."""
    n_boot = len(indices)
    flat = (indices + n * np.arange(n_boot)[:, None]).ravel()
    return np.bincount(flat, minlength=n * n_boot).reshape(n_boot, n)


def iqm_distribution(tasks: Sequence[np.ndarray], indices: Sequence[np.ndarray]) -> np.ndarray:
    """The IQM of every resample: each task's resampled runs, pooled over tasks, then trimmed."""
    pooled = np.concatenate([x[idx] for x, idx in zip(tasks, indices)], axis=1)
    return iqm(pooled, axis=1)


def improvement_matrix(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """1 where x_i > y_j, ½ where x_i = y_j, 0 otherwise: a (len(x), len(y)) array."""
    return (x[:, None] > y[None, :]) + 0.5 * (x[:, None] == y[None, :])


def poi_unpaired(tasks: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    """P(X > Y) + ½ P(X = Y) of a run X of A and a run Y of B in the same task, averaged over tasks."""
    return float(np.mean([improvement_matrix(x, y).mean() for x, y in tasks]))


def poi_unpaired_distribution(tasks: Sequence[tuple[np.ndarray, np.ndarray]], indices_a: Sequence[np.ndarray],
                              indices_b: Sequence[np.ndarray]) -> np.ndarray:
    """poi_unpaired of every resample; A's and B's runs are resampled independently within each task.

    Per resample, each drawn run x of A scores the share of B's drawn runs below x plus half the
    share equal to x (read off the cumulative draw counts of B's runs in sorted order); the task's
    value is the mean of that over A's drawn runs: the mean over all n_A × n_B pairs of drawn runs."""
    per_task = []
    for (x, y), ia, ib in zip(tasks, indices_a, indices_b):
        order = np.argsort(y, kind="stable")
        below = np.searchsorted(y[order], x, side="left")  # B's runs, in sorted order, below x: [0, below)
        upto = np.searchsorted(y[order], x, side="right")  # … and up to x: [0, upto)
        counts = draw_counts(ib, len(y))[:, order]
        cum = np.concatenate([np.zeros((len(counts), 1)), np.cumsum(counts, axis=1)], axis=1)
        share = (cum[:, below] + 0.5 * (cum[:, upto] - cum[:, below])) / len(y)  # (n_boot, n_A): per run of A
        per_task.append(np.take_along_axis(share, ia, axis=1).mean(axis=1))
    return np.mean(per_task, axis=0)


def block_wins(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per block: 1 where A's run scores higher than B's, ½ on a tie, 0 otherwise."""
    return (a > b) + 0.5 * (a == b)


def poi_paired(wins: Sequence[np.ndarray]) -> float:
    """The mean of block_wins over each task's blocks, averaged over tasks."""
    return float(np.mean([w.mean() for w in wins]))


def poi_paired_distribution(wins: Sequence[np.ndarray], indices: Sequence[np.ndarray]) -> np.ndarray:
    """poi_paired of every resample; blocks are resampled within each task."""
    return np.mean([w[idx].mean(axis=1) for w, idx in zip(wins, indices)], axis=0)


def profile(values: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """Fraction of runs whose value is > τ, for every τ."""
    return (values[:, None] > taus[None, :]).mean(axis=0)


def profile_distribution(tasks: Sequence[np.ndarray], indices: Sequence[np.ndarray], taus: np.ndarray) -> np.ndarray:
    """The profile of every resample, (n_boot, len(taus)): resampled runs pooled over tasks. Per task,
    the drawn runs above τ are all drawn runs less those at or below τ (cumulative draw counts in sorted order)."""
    above = 0.0
    for x, idx in zip(tasks, indices):
        order = np.argsort(x, kind="stable")
        cum = np.concatenate([np.zeros((len(idx), 1)), np.cumsum(draw_counts(idx, len(x))[:, order], axis=1)], axis=1)
        at_or_below = cum[:, np.searchsorted(x[order], taus, side="right")]
        above = above + (cum[:, -1:] - at_or_below)
    return above / sum(len(x) for x in tasks)


# ---- the same, with their intervals ------------------------------------------------------------------

def bootstrap_iqm(tasks: Sequence[np.ndarray], n_boot: int, ci: float, seed: int) -> tuple[float, float, float]:
    """IQM of the pooled runs of the tasks and its stratified-bootstrap interval: (point, low, high)."""
    tasks = [np.asarray(x, dtype=float) for x in tasks if len(x)]
    if not tasks:
        return (np.nan,) * 3
    indices = stratified_indices([len(x) for x in tasks], n_boot, np.random.default_rng(seed))
    lo, hi = percentile_interval(iqm_distribution(tasks, indices), ci)
    return float(iqm(np.concatenate(tasks), axis=None)), float(lo), float(hi)


def bootstrap_poi_unpaired(tasks: Sequence[tuple[np.ndarray, np.ndarray]], n_boot: int, ci: float,
                           seed: int) -> tuple[float, float, float]:
    """Unpaired P(A > B) over tasks with its stratified, independent-samples bootstrap interval."""
    tasks = [(np.asarray(x, float), np.asarray(y, float)) for x, y in tasks if len(x) and len(y)]
    if not tasks:
        return (np.nan,) * 3
    rng = np.random.default_rng(seed)
    ia = stratified_indices([len(x) for x, _ in tasks], n_boot, rng)
    ib = stratified_indices([len(y) for _, y in tasks], n_boot, rng)
    lo, hi = percentile_interval(poi_unpaired_distribution(tasks, ia, ib), ci)
    return poi_unpaired(tasks), float(lo), float(hi)


def bootstrap_profile(tasks: Sequence[np.ndarray], taus: np.ndarray, n_boot: int, ci: float,
                      seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Performance profile of the pooled runs and its stratified-bootstrap band: (fraction, low, high)."""
    tasks = [np.asarray(x, dtype=float) for x in tasks if len(x)]
    indices = stratified_indices([len(x) for x in tasks], n_boot, np.random.default_rng(seed))
    lo, hi = percentile_interval(profile_distribution(tasks, indices, taus), ci)
    return profile(np.concatenate(tasks), taus), lo, hi


# ---- the normalised score ------------------------------------------------------------------------------

def anchors(rows: pd.DataFrame, metric: str, higher: bool) -> tuple[float, str, float, str]:
    """(zero, its rule, one, its rule) of one condition's rows, in score units (see the module docstring)."""
    least = int(rows["paired"].min())
    pc = rows[rows["method"] == "pc"]
    at = pc[pc["paired"] == pc["paired"].min()] if len(pc) else rows[rows["paired"] == least]
    where = f"{int(at['paired'].iloc[0])} paired"
    zero = float(at["score"].median())
    zero_rule = f"median of PC at {where}" if len(pc) else f"median of all treatments at {where} (no PC rows)"
    base = rows["eval_self_play_base"] if "eval_self_play_base" in rows else pd.Series(dtype=float)
    base = pd.to_numeric(base, errors="coerce").dropna()
    if metric.startswith("eval_mixed") and len(base):
        one = float(base.median()) * (1.0 if higher else -1.0)
        return zero, zero_rule, one, "median of the base pair's own self-play score (eval_self_play_base)"
    best = float(rows.groupby(["treatment", "paired"])["score"].median().max())
    return zero, zero_rule, best, "best (treatment, paired) median of the condition"


def normalisation_table(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> pd.DataFrame:
    """Per condition: the zero and one of the normalised score, in metric units and in score units."""
    sign = 1.0 if layout.higher_is_better else -1.0
    out = []
    for cond, g in by_condition(rows):
        zero, zero_rule, one, one_rule = anchors(g, cfg.metric, layout.higher_is_better)
        usable = bool(np.isfinite(zero) and np.isfinite(one) and one != zero)
        out.append({"domain": layout.domain, "condition": cond, "metric": cfg.metric,
                    "higher_is_better": layout.higher_is_better, "zero": sign * zero, "zero_rule": zero_rule,
                    "one": sign * one, "one_rule": one_rule, "zero_score": zero, "one_score": one,
                    "usable": usable, "note": "" if usable else "zero and one coincide: no normalised score"})
    return pd.DataFrame(out)


def normalise(rows: pd.DataFrame, norm: pd.DataFrame) -> pd.Series:
    """The normalised score of every row, from its domain's and condition's anchors (NaN where unusable)."""
    keys = norm.set_index(["domain", "condition"])
    zero = keys["zero_score"].reindex(pd.MultiIndex.from_frame(rows[["domain", "condition"]])).to_numpy()
    one = keys["one_score"].reindex(pd.MultiIndex.from_frame(rows[["domain", "condition"]])).to_numpy()
    usable = keys["usable"].reindex(pd.MultiIndex.from_frame(rows[["domain", "condition"]])).to_numpy(bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        value = (rows["score"].to_numpy(float) - zero) / (one - zero)
    return pd.Series(np.where(usable, value, np.nan), index=rows.index, name="norm")


# ---- the tables ---------------------------------------------------------------------------------------

def in_paired_range(rows: pd.DataFrame, cfg: StatsConfig, domain: str) -> pd.DataFrame:
    """The rows of the domain's paired range (the rank tests' range: the paper's, or --paired-range)."""
    lo, hi = paired_range_for(domain, cfg, rows["paired"].unique())
    return rows[(rows["paired"] >= lo) & (rows["paired"] <= hi)]


def iqm_table(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout, norm: pd.DataFrame) -> pd.DataFrame:
    """Per (condition, treatment, paired): IQM over trials with its bootstrap interval, in metric units
    and normalised. One bootstrap of the score; both scales are affine maps of it (the IQM and the
    percentiles follow an affine map, an order-reversing one swapping low and high)."""
    sign = 1.0 if layout.higher_is_better else -1.0
    anchor = norm.set_index("condition")
    out = []
    for (cond, treat, paired), g in rows.groupby(["condition", "treatment", "paired"], sort=False):
        point, lo, hi = bootstrap_iqm([g["score"].to_numpy(float)], cfg.n_boot, cfg.ci,
                                      group_seed(cfg.seed, "iqm", layout.domain, cond, treat, paired))
        zero, one = anchor.loc[cond, "zero_score"], anchor.loc[cond, "one_score"]
        scale = 1.0 / (one - zero) if anchor.loc[cond, "usable"] else np.nan
        n_lo, n_hi = sorted([(lo - zero) * scale, (hi - zero) * scale]) if np.isfinite(scale) else (np.nan,) * 2
        m_lo, m_hi = sorted([sign * lo, sign * hi])
        out.append({"domain": layout.domain, "condition": cond, "method": g["method"].iloc[0], "treatment": treat,
                    "paired": int(paired), "metric": cfg.metric, "higher_is_better": layout.higher_is_better,
                    "n": len(g), "iqm": sign * point, "ci_low": m_lo, "ci_high": m_hi,
                    "iqm_norm": (point - zero) * scale, "norm_ci_low": n_lo, "norm_ci_high": n_hi})
    df = pd.DataFrame(out)
    order = {t: i for i, t in enumerate(treatment_order(df["treatment"]))}
    conditions = {c: i for i, (c, _) in enumerate(by_condition(rows))}
    df = df.assign(_c=df["condition"].map(conditions), _t=df["treatment"].map(order))
    return df.sort_values(["_c", "_t", "paired"], kind="stable").drop(columns=["_c", "_t"]).reset_index(drop=True)


def ordered_pairs(treatments: Sequence[str]) -> list[tuple[str, str]]:
    """Every pair of treatments, ASP first (as in the pairwise table), else in treatment order."""
    pairs = []
    for a, b in combinations(treatment_order(treatments), 2):
        pairs.append((b, a) if is_asp(b) and not is_asp(a) else (a, b))
    return pairs


def block_table(rows: pd.DataFrame) -> dict[int, pd.DataFrame]:
    """paired count -> its blocks × treatments table of scores (NaN where a block lacks a treatment)."""
    wide = rows.pivot_table(index=["paired", "root_seed", "trial"], columns="treatment", values="score",
                            aggfunc="mean")
    return {int(p): block for p, block in wide.groupby(level="paired", sort=True)}


def pair_tasks(blocks: dict[int, pd.DataFrame], a: str, b: str) -> tuple[list, list, list[int]]:
    """Per paired count with runs of both: (A's runs, B's runs), the block wins of A over B, the count."""
    runs, wins, counts = [], [], []
    for paired, block in blocks.items():
        if a not in block or b not in block:
            continue
        x, y = block[a].to_numpy(float), block[b].to_numpy(float)
        both = ~np.isnan(x) & ~np.isnan(y)
        if np.isnan(x).all() or np.isnan(y).all():
            continue
        runs.append((x[~np.isnan(x)], y[~np.isnan(y)]))
        wins.append(block_wins(x[both], y[both]))
        counts.append(paired)
    return runs, wins, counts


@dataclass
class TaskImprovement:
    """P(A > B) of one task, unpaired and paired, with the resampled values behind their intervals."""

    paired: int
    n_runs_a: int
    n_runs_b: int
    n_blocks: int
    poi: float
    poi_dist: np.ndarray
    poi_paired: float
    poi_paired_dist: np.ndarray


def task_improvement(run: tuple[np.ndarray, np.ndarray], wins: np.ndarray, paired: int, n_boot: int,
                     seed: int) -> TaskImprovement:
    """Resample one task: A's and B's runs independently (unpaired), its blocks (paired)."""
    rng = np.random.default_rng(seed)
    x, y = run
    dist = poi_unpaired_distribution([run], stratified_indices([len(x)], n_boot, rng),
                                     stratified_indices([len(y)], n_boot, rng))
    if len(wins):
        paired_dist = poi_paired_distribution([wins], stratified_indices([len(wins)], n_boot, rng))
    else:
        paired_dist = np.full(n_boot, np.nan)
    return TaskImprovement(paired, len(x), len(y), len(wins), poi_unpaired([run]),
                           dist, poi_paired([wins]) if len(wins) else np.nan, paired_dist)


def improvement_record(tasks: Sequence[TaskImprovement], ci: float) -> dict:
    """P(A > B) over tasks: the mean of the tasks' values, and its interval from the means of their
    resamples (every task is resampled independently of the others: the stratified bootstrap).
    The paired form averages the tasks that have blocks."""
    lo, hi = percentile_interval(np.mean([t.poi_dist for t in tasks], axis=0), ci)
    with_blocks = [t for t in tasks if t.n_blocks]
    if with_blocks:
        pp = float(np.mean([t.poi_paired for t in with_blocks]))
        plo, phi = percentile_interval(np.mean([t.poi_paired_dist for t in with_blocks], axis=0), ci)
    else:
        pp = plo = phi = np.nan
    return {"n_tasks": len(tasks), "n_runs_a": sum(t.n_runs_a for t in tasks),
            "n_runs_b": sum(t.n_runs_b for t in tasks), "poi": float(np.mean([t.poi for t in tasks])),
            "poi_ci_low": float(lo), "poi_ci_high": float(hi), "n_blocks": sum(t.n_blocks for t in tasks),
            "poi_paired": pp, "poi_paired_ci_low": float(plo), "poi_paired_ci_high": float(phi)}


def improvement_tables(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> tuple[pd.DataFrame, pd.DataFrame]:
    """P(A > B) for every pair: per paired count, and pooled over the paired range (its counts as tasks,
    from the same resamples as the per-count rows)."""
    pooled, per_count = [], []
    for cond, g in by_condition(rows):
        lo, hi = paired_range_for(layout.domain, cfg, g["paired"].unique())
        blocks = block_table(g)
        for a, b in ordered_pairs(g["treatment"].unique()):
            runs, wins, counts = pair_tasks(blocks, a, b)
            tasks = [task_improvement(r, w, p, cfg.n_boot, group_seed(cfg.seed, "poi", layout.domain, cond, a, b, p))
                     for r, w, p in zip(runs, wins, counts)]
            key = {"domain": layout.domain, "condition": cond}
            per_count.extend({**key, "paired": t.paired, "a": a, "b": b, **improvement_record([t], cfg.ci)}
                             for t in tasks)
            in_range = [t for t in tasks if lo <= t.paired <= hi]
            if in_range:
                pooled.append({**key, "paired_range": f"{lo}-{hi}", "a": a, "b": b,
                               **improvement_record(in_range, cfg.ci)})
    return pd.DataFrame(pooled), pd.DataFrame(per_count)


def range_tasks(rows: pd.DataFrame, cfg: StatsConfig) -> pd.DataFrame:
    """The rows of every domain's paired range, with a normalised score (rows of unusable anchors left out)."""
    parts = [in_paired_range(g, cfg, domain) for domain, g in rows.groupby("domain", sort=True)]
    kept = pd.concat(parts, ignore_index=True)
    return kept[kept["norm"].notna()]


def scopes(rows: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """"all domains" (when there are several), then each domain on its own."""
    each = [(domain, g) for domain, g in rows.groupby("domain", sort=True)]
    return ([("all domains", rows)] if len(each) > 1 else []) + each


def aggregate_table(rows: pd.DataFrame, cfg: StatsConfig) -> pd.DataFrame:
    """IQM of the normalised score per treatment, pooled over the tasks (domain, condition, paired) of
    every domain's paired range, with the stratified bootstrap; over all domains and per domain."""
    out = []
    for scope, g in scopes(range_tasks(rows, cfg)):
        for treat in treatment_order(g["treatment"]):
            t = g[g["treatment"] == treat]
            tasks = [x["norm"].to_numpy(float) for _, x in t.groupby(["domain", "condition", "paired"], sort=True)]
            point, lo, hi = bootstrap_iqm(tasks, cfg.n_boot, cfg.ci, group_seed(cfg.seed, "aggregate", scope, treat))
            out.append({"scope": scope, "treatment": treat, "domains": ", ".join(sorted(t["domain"].unique())),
                        "n_tasks": len(tasks), "n_runs": len(t), "iqm_norm": point, "ci_low": lo, "ci_high": hi})
    return pd.DataFrame(out)


def tau_grid(values: np.ndarray) -> np.ndarray:
    """TAU_POINTS thresholds from min(0, lowest) to max(1, highest), clipped to TAU_LIMITS."""
    lo = max(TAU_LIMITS[0], min(0.0, float(np.min(values))))
    hi = min(TAU_LIMITS[1], max(1.0, float(np.max(values))))
    return np.linspace(lo, hi, TAU_POINTS)


def profile_table(rows: pd.DataFrame, cfg: StatsConfig) -> pd.DataFrame:
    """Performance profiles of the normalised score per treatment and scope (tasks of the paired ranges)."""
    out = []
    for scope, g in scopes(range_tasks(rows, cfg)):
        taus = tau_grid(g["norm"].to_numpy(float))
        for treat in treatment_order(g["treatment"]):
            t = g[g["treatment"] == treat]
            tasks = [x["norm"].to_numpy(float) for _, x in t.groupby(["domain", "condition", "paired"], sort=True)]
            frac, lo, hi = bootstrap_profile(tasks, taus, cfg.n_boot, cfg.ci,
                                             group_seed(cfg.seed, "profile", scope, treat))
            out.extend({"scope": scope, "treatment": treat, "tau": float(tau), "fraction": float(f),
                        "ci_low": float(a), "ci_high": float(b), "n_runs": len(t)}
                       for tau, f, a, b in zip(taus, frac, lo, hi))
    return pd.DataFrame(out)


def interval_call(low: float, high: float, a: str, b: str) -> str:
    """What an interval of P(A > B) says: A better (above ½), B better (below ½), or uncertain."""
    if low > 0.5:
        return f"{a} better"
    if high < 0.5:
        return f"{b} better"
    return "uncertain" if np.isfinite(low) and np.isfinite(high) else "–"


def rank_call(rec: pd.Series, flag: str) -> str:
    """The rank tests' call on a pair: the better treatment where `flag` says significant, else n.s."""
    if bool(rec.get(flag)) and rec["better"] in (rec["a"], rec["b"]):
        return f"{rec['better']} better"
    return "n.s."


def agreement_table(improvement: pd.DataFrame, pairwise: pd.DataFrame) -> pd.DataFrame:
    """Per pair and condition: the calls of P(A > B)'s intervals beside the rank tests' verdicts."""
    if improvement.empty or pairwise.empty:
        return pd.DataFrame()
    keys = ["domain", "condition", "a", "b"]
    both = improvement.merge(pairwise[keys + ["n_blocks", "better", "significant", "significant_wilcoxon_holm",
                                             "p_nemenyi", "p_holm"]].rename(columns={"n_blocks": "rank_blocks"}),
                             on=keys, how="inner")
    out = []
    for rec in both.to_dict("records"):
        paired = interval_call(rec["poi_paired_ci_low"], rec["poi_paired_ci_high"], rec["a"], rec["b"])
        unpaired = interval_call(rec["poi_ci_low"], rec["poi_ci_high"], rec["a"], rec["b"])
        nemenyi = pd.notna(rec["p_nemenyi"])
        primary = rank_call(pd.Series(rec), "significant")
        out.append({"domain": rec["domain"], "condition": rec["condition"], "paired_range": rec["paired_range"],
                    "a": rec["a"], "b": rec["b"], "n_blocks": rec["n_blocks"], "poi_paired": rec["poi_paired"],
                    "poi_paired_ci_low": rec["poi_paired_ci_low"], "poi_paired_ci_high": rec["poi_paired_ci_high"],
                    "rliable_paired": paired, "poi": rec["poi"], "poi_ci_low": rec["poi_ci_low"],
                    "poi_ci_high": rec["poi_ci_high"], "rliable_unpaired": unpaired,
                    "rank_test": "Friedman + Nemenyi" if nemenyi else "Wilcoxon", "rank_call": primary,
                    "wilcoxon_holm_call": rank_call(pd.Series(rec), "significant_wilcoxon_holm"),
                    "agree_paired": _same(paired, primary), "agree_unpaired": _same(unpaired, primary)})
    return pd.DataFrame(out)


def _same(interval: str, rank: str) -> bool:
    """An interval call and a rank-test call agree: the same winner, or neither calls one."""
    return interval == rank or (interval == "uncertain" and rank == "n.s.")


def rliable_tables(rows: pd.DataFrame, cfg: StatsConfig, layouts: dict[str, DomainLayout],
                   pairwise: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """Every table of the rliable view, from the labelled rows of all domains (job.compute)."""
    norms, iqms, pooled, per_count, normed = [], [], [], [], []
    for domain, g in rows.groupby("domain", sort=True):
        layout = layouts[domain]
        norm = normalisation_table(g, cfg, layout)
        norms.append(norm)
        normed.append(g.assign(norm=normalise(g, norm)))
        iqms.append(iqm_table(g, cfg, layout, norm))
        pool, count = improvement_tables(g, cfg, layout)
        pooled.append(pool)
        per_count.append(count)
    all_rows = pd.concat(normed, ignore_index=True)
    improvement = _concat(pooled)
    return {"normalisation": _concat(norms), "iqm": _concat(iqms), "aggregate": aggregate_table(all_rows, cfg),
            "improvement": improvement, "improvement_by_paired": _concat(per_count),
            "profiles": profile_table(all_rows, cfg), "rliable_agreement": agreement_table(improvement, pairwise)}


def _concat(dfs: list[pd.DataFrame]) -> pd.DataFrame:
    present = [df for df in dfs if not df.empty]
    return pd.concat(present, ignore_index=True) if present else pd.DataFrame()
