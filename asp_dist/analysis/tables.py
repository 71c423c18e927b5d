"""The per-domain tables of the stats job, from labelled rows (layout.py) and the settings that shape them.

Differences are paired over blocks. In `pairwise`, `by_paired` and `knob_trend` they are in
metric units, a − b (so negative means a is better when lower is better; `better` says who won).
In `claim_2n` they are ASP's *gain* instead, positive = ASP better for either metric direction,
so that the verdict and the interval beside it always agree in sign.

A method's ``@default`` arm (its *companion*, layout.is_companion) is left out of the main tests (rank
tests, by_paired, claim_2n, knob trends), which compare the methods as the paper does; `default_vs_tuned`
compares each companion with its method alone.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Sequence

import numpy as np
import pandas as pd

from asp_dist.analysis.layout import (
    DomainLayout,
    base_method,
    by_condition,
    condition_key,
    fmt_value,
    is_asp,
    is_companion,
    treatment_order,
)
from asp_dist.analysis.paper import paper_paired_ranges, paper_threshold
from asp_dist.analysis.rank_tests import (
    bootstrap_median_ci,
    friedman,
    group_seed,
    holm,
    mean_ranks,
    nemenyi,
    quartiles,
    spearman,
    wilcoxon,
)


@dataclass
class StatsConfig:
    metric: str = "eval_mixed"
    # domain -> paired counts of the rank tests; None or absent: every count. Default: the paper's ranges.
    paired_ranges: dict[str, tuple[int, int] | None] = field(default_factory=paper_paired_ranges)
    thresholds: dict[str, float] = field(default_factory=dict)  # user-given data-efficiency thresholds
    alpha: float = 0.05
    n_boot: int = 2000
    ci: float = 0.95
    seed: int = 0


def summary_table(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> pd.DataFrame:
    out = []
    keys = ["condition", "treatment", "paired"]
    for (cond, treat, paired), g in rows.groupby(keys, sort=False, dropna=False):
        x = g[cfg.metric].astype(float).dropna().to_numpy()
        q1, med, q3 = quartiles(x) if len(x) else (np.nan,) * 3
        lo, hi = bootstrap_median_ci(x, cfg.n_boot, cfg.ci, group_seed(cfg.seed, layout.domain, cond, treat, paired))
        rec = {"domain": layout.domain, "condition": cond, "method": g["method"].iloc[0], "treatment": treat,
               "paired": int(paired)}
        for k in layout.shared_knobs + layout.method_knobs.get(g["method"].iloc[0], []):
            rec[k] = g[k].iloc[0]
        rec.update({"metric": cfg.metric, "higher_is_better": layout.higher_is_better, "n": int(len(x)),
                    "median": med, "q1": q1, "q3": q3, "mean": float(np.mean(x)) if len(x) else np.nan,
                    "std": float(np.std(x, ddof=1)) if len(x) > 1 else np.nan, "ci_low": lo, "ci_high": hi})
        out.append(rec)
    df = pd.DataFrame(out)
    order = {t: i for i, t in enumerate(treatment_order(df["treatment"]))}
    df["_order"] = df["treatment"].map(order)
    conditions = {c: i for i, c in enumerate(sorted(df["condition"].unique(), key=condition_key))}
    df["_cond"] = df["condition"].map(conditions)
    df = df.sort_values(["_cond", "_order", "paired"], kind="stable")
    return df.drop(columns=["_order", "_cond"]).reset_index(drop=True)


# ---- rank tests ------------------------------------------------------------------------------------

def main_rows(rows: pd.DataFrame) -> pd.DataFrame:
    """The rows of the main tests: every treatment but the companions (``osp@default``)."""
    return rows[~rows["treatment"].map(is_companion)] if len(rows) else rows


def paired_range_for(domain: str, cfg: StatsConfig, available: Sequence[int]) -> tuple[int, int]:
    rng = cfg.paired_ranges.get(domain)
    if rng is None:
        return int(min(available)), int(max(available))
    return rng


def block_matrix(rows: pd.DataFrame, treatments: Sequence[str]) -> pd.DataFrame:
    """Blocks x treatments table of scores; only complete blocks (every treatment present)."""
    wide = rows.pivot_table(index=["root_seed", "trial", "paired"], columns="treatment", values="score", aggfunc="mean")
    wide = wide.reindex(columns=list(treatments))
    return wide.dropna()


def pair_stats(wide: pd.DataFrame, a: str, b: str, higher: bool) -> dict[str, Any]:
    """Wilcoxon of a against b over blocks; medians in metric units, median_diff in score units (> 0: a better)."""
    diff = (wide[a] - wide[b]).to_numpy()
    stat, p = wilcoxon(diff)
    sign = 1.0 if higher else -1.0
    return {"n_blocks": int(len(diff)), "median_a": float(np.median(sign * wide[a])) if len(diff) else np.nan,
            "median_b": float(np.median(sign * wide[b])) if len(diff) else np.nan,
            "median_diff": float(np.median(diff)) if len(diff) else np.nan,
            "wins_a": int((diff > 0).sum()), "ties": int((diff == 0).sum()), "wins_b": int((diff < 0).sum()),
            "wilcoxon_stat": stat, "p_wilcoxon": p}


def better_of(a: str, b: str, wins_a: int, wins_b: int, median_diff: float) -> str:
    """The better treatment, from the median score difference a − b (wins break a zero median)."""
    if median_diff > 0 or (median_diff == 0 and wins_a > wins_b):
        return a
    if median_diff < 0 or (median_diff == 0 and wins_b > wins_a):
        return b
    return "tie"


def rank_tests(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> tuple[list[dict], list[dict]]:
    """Friedman (or the two-treatment Wilcoxon) per condition over the paired range, with post-hocs."""
    omnibus, pairwise = [], []
    sign = 1.0 if layout.higher_is_better else -1.0
    for cond, g in by_condition(main_rows(rows)):
        lo, hi = paired_range_for(layout.domain, cfg, g["paired"].unique())
        in_range = g[(g["paired"] >= lo) & (g["paired"] <= hi)]
        treatments = treatment_order(in_range["treatment"])
        base = {"domain": layout.domain, "condition": cond, "metric": cfg.metric,
                "higher_is_better": layout.higher_is_better, "paired_range": f"{lo}-{hi}",
                "treatments": ", ".join(treatments)}
        if len(treatments) < 2:
            omnibus.append({**base, "test": "none", "n_blocks": 0, "note": "fewer than two treatments in range"})
            continue
        all_blocks = in_range.groupby(["root_seed", "trial", "paired"]).ngroups
        wide = block_matrix(in_range, treatments)
        n = len(wide)
        rec = {**base, "n_blocks": n, "n_blocks_incomplete": all_blocks - n}
        if n < 2:
            omnibus.append({**rec, "test": "none", "note": "fewer than two complete blocks"})
            continue
        scores = wide.to_numpy()
        nem = None
        if len(treatments) >= 3:
            stat, p = friedman(scores)
            ranks = mean_ranks(scores)
            rec.update({"test": "friedman", "statistic": stat, "p_value": p,
                        "kendall_w": stat / (n * (len(treatments) - 1)),
                        "mean_ranks": json.dumps({t: round(float(r), 3) for t, r in zip(treatments, ranks)})})
            nem = nemenyi(scores)
        else:
            a, b = treatments
            ps = pair_stats(wide, a, b, layout.higher_is_better)
            rec.update({"test": "wilcoxon", "statistic": ps["wilcoxon_stat"], "p_value": ps["p_wilcoxon"],
                        "note": "two treatments: Wilcoxon signed-rank over blocks"})
        omnibus.append(rec)
        found = []
        for a, b in combinations(treatments, 2):
            # Put ASP first so that "positive difference" reads as "ASP better".
            if is_asp(b) and not is_asp(a):
                a, b = b, a
            ps = pair_stats(wide, a, b, layout.higher_is_better)
            ps["p_nemenyi"] = float(nem[treatments.index(a), treatments.index(b)]) if nem is not None else np.nan
            found.append({**base, "a": a, "b": b, **ps})
        # Primary view (the paper's): Friedman, then Nemenyi. Second view: Wilcoxon + Holm.
        # With two treatments the Wilcoxon test is the only view.
        omnibus_ok = rec["test"] != "friedman" or rec.get("p_value", np.nan) < cfg.alpha
        for f, p_holm in zip(found, holm([f["p_wilcoxon"] for f in found])):
            score_diff = f["median_diff"]
            f["median_diff"] = sign * score_diff  # back to metric units (a − b)
            f["p_holm"] = float(p_holm)
            f["better"] = better_of(f["a"], f["b"], f["wins_a"], f["wins_b"], score_diff)
            f["significant_wilcoxon_holm"] = bool(omnibus_ok and p_holm < cfg.alpha)
            if rec["test"] == "friedman":
                f["significant_nemenyi"] = bool(omnibus_ok and f["p_nemenyi"] < cfg.alpha)
                f["significant"] = f["significant_nemenyi"]
            else:
                f["significant_nemenyi"] = None
                f["significant"] = f["significant_wilcoxon_holm"]
            f["views_agree"] = f["significant"] == f["significant_wilcoxon_holm"]
        pairwise.extend(found)
    return omnibus, pairwise


def by_paired_table(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> list[dict]:
    """ASP against each other treatment at every paired count (where does ASP help?), Holm per condition."""
    out = []
    sign = 1.0 if layout.higher_is_better else -1.0
    for cond, g in by_condition(main_rows(rows)):
        treatments = treatment_order(g["treatment"])
        asps = [t for t in treatments if is_asp(t)]
        pairs = ([(a, b) for a in asps for b in treatments if not is_asp(b)] if asps
                 else list(combinations(treatments, 2)))
        found = []
        for paired, gp in g.groupby("paired", sort=True):
            for a, b in pairs:
                wide = block_matrix(gp, [a, b])
                if len(wide) == 0:
                    continue
                ps = pair_stats(wide, a, b, layout.higher_is_better)
                found.append({"domain": layout.domain, "condition": cond, "paired": int(paired), "a": a, "b": b,
                              **ps, "median_diff": sign * ps["median_diff"],
                              "better": better_of(a, b, ps["wins_a"], ps["wins_b"], ps["median_diff"])})
        for f, p in zip(found, holm([f["p_wilcoxon"] for f in found])):
            f["p_holm"] = float(p)
            f["significant"] = bool(p < cfg.alpha)
        out.extend(found)
    return out


# ---- data efficiency -------------------------------------------------------------------------------

def threshold_for(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout,
                  summary: pd.DataFrame) -> tuple[float, str]:
    """The user's threshold, else the paper's (PaperFacts), else 90% of the base's self-play, else halfway."""
    if layout.domain in cfg.thresholds:
        return float(cfg.thresholds[layout.domain]), "user-given"
    paper = paper_threshold(layout.domain, cfg.metric)
    if paper is not None:
        return paper
    if cfg.metric == "eval_mixed" and layout.higher_is_better and "eval_self_play_base" in rows \
            and rows["eval_self_play_base"].notna().any():
        base = float(rows["eval_self_play_base"].median())
        return 0.9 * base, f"90% of the base pair's median self-play score ({base:.4g})"
    lo, hi = summary["median"].min(), summary["median"].max()
    return float((lo + hi) / 2), "halfway between the worst and best group median"


def efficiency_table(summary: pd.DataFrame, threshold: tuple[float, str], cfg: StatsConfig,
                     layout: DomainLayout) -> list[dict]:
    """The smallest paired count whose group median reaches the threshold, per (condition, treatment)."""
    thr, rule = threshold
    higher = layout.higher_is_better
    out = []
    for (cond, treat), g in summary.groupby(["condition", "treatment"], sort=False):
        g = g.sort_values("paired")
        hit = g[g["median"] >= thr] if higher else g[g["median"] <= thr]
        out.append({"domain": layout.domain, "condition": cond, "treatment": treat, "metric": cfg.metric,
                    "threshold": thr, "threshold_rule": rule, "higher_is_better": higher,
                    "paired_counts": ", ".join(str(p) for p in g["paired"]),
                    "min_paired_reaching": int(hit["paired"].iloc[0]) if len(hit) else None,
                    "median_there": float(hit["median"].iloc[0]) if len(hit) else None})
    return out


def per_trial(rows: pd.DataFrame, treatment: str, paired: int) -> pd.Series:
    """Mean score per (root_seed, trial) of one treatment at one paired count."""
    at = rows[(rows["treatment"] == treatment) & (rows["paired"] == paired)]
    return at.groupby(["root_seed", "trial"])["score"].mean()


def claim_2n_table(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> list[dict]:
    """The paper's claim, ASP with n paired examples matches or beats another method with 2n.

    `median_gain` and its interval `gain_ci_low`..`gain_ci_high` are ASP's improvement over the
    other method, per trial, in metric units with positive = ASP better whichever way the metric
    points (for a lower-is-better metric: other's value − ASP's value). "beats" means the gain's
    whole interval is above 0."""
    higher = layout.higher_is_better
    sign = 1.0 if higher else -1.0
    out = []
    for cond, g in by_condition(main_rows(rows)):
        treatments = treatment_order(g["treatment"])
        for a in (t for t in treatments if is_asp(t)):
            for b in (t for t in treatments if not is_asp(t)):
                for n in sorted(g.loc[g["treatment"] == a, "paired"].unique()):
                    if n == 0 or not ((g["treatment"] == b) & (g["paired"] == 2 * n)).any():
                        continue
                    ga = per_trial(g, a, n)
                    gb = per_trial(g, b, 2 * n)
                    both = pd.concat([ga.rename("a"), gb.rename("b")], axis=1).dropna()
                    gain = (both["a"] - both["b"]).to_numpy()  # score units: positive = ASP better
                    lo, hi = bootstrap_median_ci(gain, cfg.n_boot, cfg.ci,
                                                 group_seed(cfg.seed, "2n", layout.domain, cond, a, b, n))
                    med_a, med_b = sign * float(np.median(ga)), sign * float(np.median(gb))
                    holds = (med_a >= med_b) if higher else (med_a <= med_b)
                    if len(gain) and lo > 0:
                        verdict = "beats (gain CI > 0)"
                    elif holds and len(gain) and hi >= 0:
                        verdict = "matches or beats (medians)"
                    else:
                        verdict = "falls short"
                    out.append({"domain": layout.domain, "condition": cond, "asp": a, "other": b, "n": int(n),
                                "two_n": int(2 * n), "median_asp_n": med_a, "median_other_2n": med_b,
                                "higher_is_better": higher, "n_trials": int(len(gain)),
                                "median_gain": float(np.median(gain)) if len(gain) else np.nan,
                                "gain_ci_low": lo, "gain_ci_high": hi, "holds": bool(holds), "verdict": verdict})
    return out


# ---- trends with a knob ------------------------------------------------------------------------------

def knob_trends(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> list[dict]:
    """Does ASP's advantage grow with a numeric knob (e.g. skew)? Spearman's rho between the knob
    and the per-block difference ASP − other (all paired counts), per value of the other knobs."""
    out = []
    sign = 1.0 if layout.higher_is_better else -1.0
    rows = main_rows(rows)
    for knob in layout.shared_knobs:
        values = pd.to_numeric(rows[knob], errors="coerce")
        if values.isna().any() or values.nunique() < 3:
            continue  # a rank correlation over two knob values says little; the tables show them
        others = [k for k in layout.shared_knobs if k != knob]
        groups = rows.groupby(others, sort=True, dropna=False) if others else [("", rows)]
        for key, g in groups:
            values = key if isinstance(key, tuple) else (key,)
            fixed = ", ".join(f"{k}={fmt_value(v)}" for k, v in zip(others, values)) if others else "all"
            treatments = treatment_order(g["treatment"])
            for a in (t for t in treatments if is_asp(t)):
                for b in (t for t in treatments if not is_asp(t)):
                    wide = g.pivot_table(index=["root_seed", "trial", "paired", knob], columns="treatment",
                                         values="score", aggfunc="mean")
                    if a not in wide or b not in wide:
                        continue
                    diff = (wide[a] - wide[b]).dropna()
                    if len(diff) < 3:
                        continue
                    x = diff.index.get_level_values(knob).astype(float)
                    rho, p = spearman(x, diff.to_numpy())
                    lo_v, hi_v = x.min(), x.max()
                    out.append({"domain": layout.domain, "knob": knob, "fixed": fixed, "a": a, "b": b,
                                "n_blocks": int(len(diff)), "spearman_rho": rho, "p_value": p,
                                "median_diff_at_min": sign * float(np.median(diff[x == lo_v])),
                                "median_diff_at_max": sign * float(np.median(diff[x == hi_v])),
                                "knob_min": float(lo_v), "knob_max": float(hi_v)})
    return out


# ---- a method against its @default arm ---------------------------------------------------------------

def default_vs_tuned_table(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> list[dict]:
    """Each companion (``osp@default``) against every other treatment of its method (``osp``, ``osp[...]``,
    ``osp@tuned``) per condition, over the paired range's complete blocks. median_diff is tuned − default
    in score units (> 0: tuned better, whichever way the metric points); p is the two-sided Wilcoxon
    signed-rank test, uncorrected: each method's question is its own."""
    out = []
    for cond, g in by_condition(rows):
        lo, hi = paired_range_for(layout.domain, cfg, g["paired"].unique())
        in_range = g[(g["paired"] >= lo) & (g["paired"] <= hi)]
        treatments = treatment_order(in_range["treatment"])
        for default in (t for t in treatments if is_companion(t)):
            method = base_method(default)
            for tuned in (t for t in treatments if base_method(t) == method and not is_companion(t)):
                wide = block_matrix(in_range, [tuned, default])
                ps = pair_stats(wide, tuned, default, layout.higher_is_better)
                p = ps["p_wilcoxon"]
                out.append({"domain": layout.domain, "condition": cond, "method": method, "tuned": tuned,
                            "default": default, "metric": cfg.metric, "higher_is_better": layout.higher_is_better,
                            "paired_range": f"{lo}-{hi}", "n_blocks": ps["n_blocks"],
                            "tuned_better": ps["wins_a"], "tuned_worse": ps["wins_b"], "ties": ps["ties"],
                            "median_tuned": ps["median_a"], "median_default": ps["median_b"],
                            "median_diff": ps["median_diff"], "p_wilcoxon": p,
                            "better": better_of(tuned, default, ps["wins_a"], ps["wins_b"], ps["median_diff"]),
                            "significant": bool(p < cfg.alpha) if not np.isnan(p) else False})
    return out
