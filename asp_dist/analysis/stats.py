"""The statistics job: a sweep's rows -> per-group summaries, rank tests, data efficiency.

Vocabulary used throughout (and in the tables):

- *knob*: a CellSpec field other than the identity (domain, method, paired, trial, root_seed)
  that takes more than one value among a domain's rows of one method. A knob varied within
  every method (latent size, skew) defines a *condition*: methods are compared within it.
  A knob varied only within some methods (say λ1 of ASP) splits that method into *treatments*
  (``asp[lambda_unpaired=0.5]``) that are compared like methods.
- *block*: one (root_seed, trial, paired) of a condition. Within a block PC/OSP/ASP share the
  base model, the paired and unpaired sets and the initial weights, so the rank tests are
  paired over blocks (Friedman, Nemenyi, Wilcoxon signed-rank), as in the paper.
- *score*: the metric oriented so that larger is better (the negated metric when the rows say
  lower is better). Differences in the tables are in metric units with "positive = first
  treatment better".

Everything random (bootstrap intervals) is seeded from (seed, group key), so a group's interval
does not depend on which other groups are present.
"""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from scipy import stats as sps

from asp_dist.results.query import Inputs, load_rows, open_inputs, read_manifest_ids
from asp_dist.spec import FIELD_NAMES, SpecError, stable_hash

IDENTITY = ("domain", "method", "paired", "trial", "root_seed")
NOT_KNOBS = frozenset(IDENTITY) | {"record_figure_data"}
# The paper's paired ranges for the Friedman test (signaling and unknown domains: every count).
PAPER_PAIRED_RANGES: dict[str, tuple[int, int]] = {"particles": (2, 4), "levers": (4, 8), "vae": (8, 32)}
# Data-efficiency thresholds with a meaning in the paper (metric eval_mixed).
PAPER_THRESHOLDS: dict[str, tuple[float, str]] = {
    "vae": (0.06, "paper: MSE 0.06 ~ right digit"),
    "levers": (1 - 0.683, "error of the best policy without communication (1 - 0.683)"),
}
METHOD_ORDER = ("pc", "osp", "asp")


@dataclass
class StatsConfig:
    metric: str = "eval_mixed"
    paired_ranges: dict[str, tuple[int, int] | None] = field(default_factory=lambda: dict(PAPER_PAIRED_RANGES))
    thresholds: dict[str, float] = field(default_factory=dict)
    alpha: float = 0.05
    n_boot: int = 2000
    ci: float = 0.95
    seed: int = 0


@dataclass
class DomainLayout:
    """How one domain's rows are organised: direction, conditions and treatments."""

    domain: str
    higher_is_better: bool
    shared_knobs: list[str]
    method_knobs: dict[str, list[str]]  # method -> knobs varied only within (some) methods


@dataclass
class StatsResult:
    config: StatsConfig
    rows: pd.DataFrame  # deduplicated rows with added columns: condition, treatment, score
    layouts: dict[str, DomainLayout]
    tables: dict[str, pd.DataFrame]
    inputs: Inputs | None = None
    notes: list[str] = field(default_factory=list)
    grid_known: bool = False  # every input sweep had a readable manifest.json


# ---- small statistics, tested on known answers ---------------------------------------------------

def quartiles(values: Sequence[float]) -> tuple[float, float, float]:
    """(Q1, median, Q3) with linear interpolation between order statistics (numpy's default, type 7)."""
    q1, med, q3 = np.percentile(np.asarray(values, dtype=float), [25, 50, 75])
    return float(q1), float(med), float(q3)


def group_seed(seed: int, *key: Any) -> int:
    return int(stable_hash({"seed": seed, "key": [str(k) for k in key]})[:12], 16)


def bootstrap_median_ci(values: Sequence[float], n_boot: int = 2000, ci: float = 0.95, seed: int = 0) -> tuple[float, float]:
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


# ---- rows -> layout ----------------------------------------------------------------------------

def metric_direction(rows: pd.DataFrame, metric: str) -> bool:
    """True if higher is better for `metric` in these rows (one domain), read from the rows themselves."""
    domain = rows["domain"].iloc[0]
    flag_col = f"{metric}_higher_is_better"
    if flag_col in rows and rows[flag_col].notna().any():
        values = set(rows[flag_col].dropna().astype(bool))
        if len(values) > 1:
            raise SpecError(f"rows of domain {domain} disagree on whether higher {metric} is better")
        return values.pop()
    if "metric_directions" in rows:
        name = metric.removeprefix("eval_")
        found = set()
        for text in rows["metric_directions"].dropna().unique():
            try:
                found.add(json.loads(text).get(name))
            except (TypeError, ValueError, AttributeError):
                continue
        found.discard(None)
        if len(found) == 1:
            return found.pop() == "higher"
        if len(found) > 1:
            raise SpecError(f"rows of domain {domain} disagree on the direction of {metric}")
    raise SpecError(f"rows of domain {domain} do not say whether higher or lower {metric} is better "
                    f"(no {flag_col} column, no entry {metric.removeprefix('eval_')!r} in metric_directions)")


def domain_layout(rows: pd.DataFrame, metric: str) -> DomainLayout:
    domain = rows["domain"].iloc[0]
    candidates = [c for c in FIELD_NAMES if c in rows.columns and c not in NOT_KNOBS]
    methods = list(rows["method"].unique())
    shared, by_method = [], {m: [] for m in methods}
    for col in candidates:
        varied_in = [m for m in methods if rows.loc[rows["method"] == m, col].nunique(dropna=False) > 1]
        if not varied_in:
            continue
        if len(varied_in) == len(methods):
            shared.append(col)
        else:
            for m in varied_in:
                by_method[m].append(col)
    return DomainLayout(domain, metric_direction(rows, metric), shared, by_method)


def _fmt_value(v: Any) -> str:
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def label_rows(rows: pd.DataFrame, layout: DomainLayout, metric: str) -> pd.DataFrame:
    """Add `condition` (shared knob values), `treatment` (method + method-only knobs) and `score`."""
    rows = rows.copy()
    if layout.shared_knobs:
        rows["condition"] = [", ".join(f"{k}={_fmt_value(v)}" for k, v in zip(layout.shared_knobs, vals))
                             for vals in rows[layout.shared_knobs].itertuples(index=False, name=None)]
    else:
        rows["condition"] = "all"
    treatments = []
    for rec in rows.to_dict("records"):
        knobs = layout.method_knobs.get(rec["method"], [])
        treatments.append(rec["method"] + ("[" + ", ".join(f"{k}={_fmt_value(rec[k])}" for k in knobs) + "]" if knobs else ""))
    rows["treatment"] = treatments
    values = pd.to_numeric(rows[metric], errors="coerce").astype(float)
    rows["score"] = values if layout.higher_is_better else -values
    if "root_seed" not in rows:
        rows["root_seed"] = 0
    return rows


def treatment_order(names: Sequence[str]) -> list[str]:
    def key(t: str) -> tuple:
        m = t.split("[")[0]
        return (METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER), t)

    return sorted(set(names), key=key)


def condition_key(condition: str) -> tuple:
    """Natural order of condition labels: "vae_latent_dim=8" before "vae_latent_dim=16"."""
    key = []
    for part in condition.split(", "):
        name, _, value = part.partition("=")
        try:
            key.append((name, 0, float(value), ""))
        except ValueError:
            key.append((name, 1, 0.0, value))
    return tuple(key)


def by_condition(rows: pd.DataFrame):
    """(condition, rows) in natural condition order."""
    for cond in sorted(rows["condition"].unique(), key=condition_key):
        yield cond, rows[rows["condition"] == cond]


def is_asp(treatment: str) -> bool:
    return treatment.split("[")[0] == "asp"


# ---- the tables ------------------------------------------------------------------------------------

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
    return df.sort_values(["_cond", "_order", "paired"], kind="stable").drop(columns=["_order", "_cond"]).reset_index(drop=True)


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
    diff = (wide[a] - wide[b]).to_numpy()  # score units: positive = a better
    stat, p = wilcoxon(diff)
    sign = 1.0 if higher else -1.0
    return {"n_blocks": int(len(diff)), "median_a": float(np.median(sign * wide[a])) if len(diff) else np.nan,
            "median_b": float(np.median(sign * wide[b])) if len(diff) else np.nan,
            "median_diff": float(np.median(diff)) if len(diff) else np.nan,
            "wins_a": int((diff > 0).sum()), "ties": int((diff == 0).sum()), "wins_b": int((diff < 0).sum()),
            "wilcoxon_stat": stat, "p_wilcoxon": p}


def better_of(a: str, b: str, wins_a: int, wins_b: int, median_diff: float) -> str:
    if median_diff > 0 or (median_diff == 0 and wins_a > wins_b):
        return a
    if median_diff < 0 or (median_diff == 0 and wins_b > wins_a):
        return b
    return "tie"


def rank_tests(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> tuple[list[dict], list[dict]]:
    """Friedman (or the two-treatment Wilcoxon) per condition over the paired range, with post-hocs."""
    omnibus, pairwise = [], []
    for cond, g in by_condition(rows):
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
            ranks = sps.rankdata(-scores, axis=1).mean(axis=0)  # 1 = best
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
        pairs = list(combinations(treatments, 2))
        found = []
        for a, b in pairs:
            # Put ASP first so that "positive difference" reads as "ASP better".
            if is_asp(b) and not is_asp(a):
                a, b = b, a
            ps = pair_stats(wide, a, b, layout.higher_is_better)
            ps["p_nemenyi"] = float(nem[treatments.index(a), treatments.index(b)]) if nem is not None else np.nan
            found.append({**base, "a": a, "b": b, **ps})
        adjusted = holm([f["p_wilcoxon"] for f in found])
        for f, p_holm in zip(found, adjusted):
            sign = 1.0 if layout.higher_is_better else -1.0
            f["median_diff"] = sign * f["median_diff"]  # back to metric units (a - b)
            f["p_holm"] = float(p_holm)
            f["better"] = better_of(f["a"], f["b"], f["wins_a"], f["wins_b"], sign * f["median_diff"])
            # Primary view (the paper's): Friedman, then Nemenyi. Second view: Wilcoxon + Holm.
            # With two treatments the Wilcoxon test is the only view.
            omnibus_ok = rec["test"] != "friedman" or rec.get("p_value", np.nan) < cfg.alpha
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
    for cond, g in by_condition(rows):
        treatments = treatment_order(g["treatment"])
        asps = [t for t in treatments if is_asp(t)]
        pairs = [(a, b) for a in asps for b in treatments if not is_asp(b)] if asps else list(combinations(treatments, 2))
        found = []
        for paired, gp in g.groupby("paired", sort=True):
            for a, b in pairs:
                wide = block_matrix(gp, [a, b])
                if len(wide) == 0:
                    continue
                ps = pair_stats(wide, a, b, layout.higher_is_better)
                sign = 1.0 if layout.higher_is_better else -1.0
                found.append({"domain": layout.domain, "condition": cond, "paired": int(paired), "a": a, "b": b,
                              **ps, "median_diff": sign * ps["median_diff"],
                              "better": better_of(a, b, ps["wins_a"], ps["wins_b"], ps["median_diff"])})
        for f, p in zip(found, holm([f["p_wilcoxon"] for f in found])):
            f["p_holm"] = float(p)
            f["significant"] = bool(p < cfg.alpha)
        out.extend(found)
    return out


def threshold_for(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout, summary: pd.DataFrame) -> tuple[float, str]:
    if layout.domain in cfg.thresholds:
        return float(cfg.thresholds[layout.domain]), "user-given"
    if cfg.metric == "eval_mixed" and layout.domain in PAPER_THRESHOLDS:
        return PAPER_THRESHOLDS[layout.domain]
    if cfg.metric == "eval_mixed" and layout.higher_is_better and "eval_self_play_base" in rows \
            and rows["eval_self_play_base"].notna().any():
        base = float(rows["eval_self_play_base"].median())
        return 0.9 * base, f"90% of the base pair's median self-play score ({base:.4g})"
    lo, hi = summary["median"].min(), summary["median"].max()
    return float((lo + hi) / 2), "halfway between the worst and best group median"


def efficiency_tables(rows: pd.DataFrame, summary: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> tuple[list[dict], list[dict]]:
    """(smallest paired count reaching a threshold, per treatment) and the paper's n-vs-2n claim."""
    thr, rule = threshold_for(rows, cfg, layout, summary)
    higher = layout.higher_is_better
    reaches = (lambda m: m >= thr) if higher else (lambda m: m <= thr)
    eff = []
    for (cond, treat), g in summary.groupby(["condition", "treatment"], sort=False):
        g = g.sort_values("paired")
        hit = g[g["median"].map(reaches)]
        eff.append({"domain": layout.domain, "condition": cond, "treatment": treat, "metric": cfg.metric,
                    "threshold": thr, "threshold_rule": rule, "higher_is_better": higher,
                    "paired_counts": ", ".join(str(p) for p in g["paired"]),
                    "min_paired_reaching": int(hit["paired"].iloc[0]) if len(hit) else None,
                    "median_there": float(hit["median"].iloc[0]) if len(hit) else None})
    claim = []
    sign = 1.0 if higher else -1.0
    for cond, g in by_condition(rows):
        treatments = treatment_order(g["treatment"])
        for a in (t for t in treatments if is_asp(t)):
            for b in (t for t in treatments if not is_asp(t)):
                for n in sorted(g.loc[g["treatment"] == a, "paired"].unique()):
                    if n == 0 or not ((g["treatment"] == b) & (g["paired"] == 2 * n)).any():
                        continue
                    ga = g[(g["treatment"] == a) & (g["paired"] == n)].groupby(["root_seed", "trial"])["score"].mean()
                    gb = g[(g["treatment"] == b) & (g["paired"] == 2 * n)].groupby(["root_seed", "trial"])["score"].mean()
                    both = pd.concat([ga.rename("a"), gb.rename("b")], axis=1).dropna()
                    diff = (both["a"] - both["b"]).to_numpy()
                    lo, hi = bootstrap_median_ci(diff, cfg.n_boot, cfg.ci, group_seed(cfg.seed, "2n", layout.domain, cond, a, b, n))
                    med_a, med_b = sign * float(np.median(ga)), sign * float(np.median(gb))
                    holds = (med_a >= med_b) if higher else (med_a <= med_b)
                    if len(diff) and lo > 0:
                        verdict = "beats (CI > 0)"
                    elif holds and len(diff) and hi >= 0:
                        verdict = "matches or beats (medians)"
                    else:
                        verdict = "falls short"
                    claim.append({"domain": layout.domain, "condition": cond, "asp": a, "other": b, "n": int(n),
                                  "two_n": int(2 * n), "median_asp_n": med_a, "median_other_2n": med_b,
                                  "n_trials": int(len(diff)),
                                  "median_diff": sign * float(np.median(diff)) if len(diff) else np.nan,
                                  "diff_ci_low": sign * lo if higher else -hi, "diff_ci_high": sign * hi if higher else -lo,
                                  "holds": bool(holds), "verdict": verdict})
    return eff, claim


def knob_trends(rows: pd.DataFrame, cfg: StatsConfig, layout: DomainLayout) -> list[dict]:
    """Does ASP's advantage grow with a numeric knob (e.g. skew)? Spearman's rho between the knob
    and the per-block difference ASP − other (all paired counts), per value of the other knobs."""
    out = []
    sign = 1.0 if layout.higher_is_better else -1.0
    for knob in layout.shared_knobs:
        values = pd.to_numeric(rows[knob], errors="coerce")
        if values.isna().any() or values.nunique() < 3:
            continue  # a rank correlation over two knob values says little; the tables show them
        others = [k for k in layout.shared_knobs if k != knob]
        groups = rows.groupby(others, sort=True, dropna=False) if others else [("", rows)]
        for key, g in groups:
            fixed = ", ".join(f"{k}={_fmt_value(v)}" for k, v in zip(others, key if isinstance(key, tuple) else (key,))) \
                if others else "all"
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
                    rho, p = sps.spearmanr(x, diff.to_numpy())
                    lo_v, hi_v = x.min(), x.max()
                    out.append({"domain": layout.domain, "knob": knob, "fixed": fixed, "a": a, "b": b,
                                "n_blocks": int(len(diff)), "spearman_rho": float(rho), "p_value": float(p),
                                "median_diff_at_min": sign * float(np.median(diff[x == lo_v])),
                                "median_diff_at_max": sign * float(np.median(diff[x == hi_v])),
                                "knob_min": float(lo_v), "knob_max": float(hi_v)})
    return out


# ---- completeness ---------------------------------------------------------------------------------

def read_failures(sweep_dir: Path) -> dict[str, str]:
    """cell_id -> last line of the error, from the sweep service's failed/<cell_id>.json records."""
    out = {}
    for path in sorted((Path(sweep_dir) / "failed").glob("*.json")):
        if path.name.startswith((".", "_")):
            continue
        try:
            info = json.loads(path.read_text())
            lines = str(info.get("error", "")).strip().splitlines()
            out[str(info.get("cell_id", path.stem))] = (lines[-1] if lines else "failed")[:160]
        except (OSError, ValueError, AttributeError):
            out[path.stem] = "failed (unreadable record)"
    return out


CELL_ID = re.compile(r"^(?P<domain>[a-z]+)-(?P<method>[a-z]+)-p(?P<paired>\d+)-t(?P<trial>\d+)-")


def completeness(rows: pd.DataFrame, inputs: Inputs | None,
                 layouts: dict[str, DomainLayout] | None = None) -> tuple[pd.DataFrame, list[str]]:
    """Missing cells: manifest ids without a row and failed cells (per sweep), and blocks lacking a treatment."""
    missing, notes = [], []
    layouts = layouts or {}
    for sweep in (inputs.sweep_dirs if inputs is not None else []):
        expected = read_manifest_ids(sweep)
        specs = read_manifest_specs(sweep)
        failed = read_failures(sweep)
        cells_dir = (sweep / "cells").resolve()
        # The store names every file <cell_id>.parquet (its own completeness check relies on it too).
        found = {f.stem for f in inputs.files if cells_dir in f.parents}
        if expected is None:
            notes.append(f"{sweep.name}: no readable manifest.json, the planned grid is unknown; "
                         "only failed cells and incomplete blocks are reported")
            gone = [c for c in failed if c not in found]
        else:
            gone = [c for c in dict.fromkeys(expected) if c not in found]
            notes.append(f"{sweep.name}: {len(set(expected)) - len(gone)} of {len(set(expected))} planned cells "
                         "finished" + (f", {len(gone)} missing" if gone else ""))
        if failed:
            notes.append(f"{sweep.name}: {len(failed)} cell(s) recorded as failed under failed/")
        for cid in gone:
            missing.append({"sweep": sweep.name, "kind": "failed" if cid in failed else "not finished (manifest)",
                            "cell_id": cid, "error": failed.get(cid), **describe_cell(cid, specs.get(cid), layouts)})
    for domain, in_domain in rows.groupby("domain", sort=True):
        for cond, g in by_condition(in_domain):
            treatments = treatment_order(g["treatment"])
            for (seed, trial, paired), b in g.groupby(["root_seed", "trial", "paired"], sort=True):
                for t in treatments:
                    if t not in set(b["treatment"]):
                        missing.append({"sweep": "", "kind": "incomplete block", "cell_id": None, "domain": domain,
                                        "method": t, "paired": int(paired), "trial": int(trial), "condition": cond})
    cols = ["sweep", "kind", "domain", "condition", "method", "paired", "trial", "cell_id", "error"]
    df = pd.DataFrame(missing, columns=cols)
    # A manifest-missing cell also leaves its block incomplete; keep both views, they answer different questions.
    return df, notes


def read_manifest_specs(sweep_dir: Path) -> dict[str, dict]:
    """cell_id -> resolved spec dict when the manifest stores "specs" aligned with "cells", else {}."""
    try:
        data = json.loads((Path(sweep_dir) / "manifest.json").read_text())
        ids, specs = data["cells"], data["specs"]
        if isinstance(ids, list) and isinstance(specs, list) and len(ids) == len(specs):
            return {str(i): s for i, s in zip(ids, specs) if isinstance(s, dict)}
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return {}


def describe_cell(cell_id: str, spec: dict | None, layouts: dict[str, DomainLayout]) -> dict[str, Any]:
    """domain, method, paired, trial (and the condition, when the domain's knobs are known) of a missing cell."""
    if spec:
        out = {k: spec.get(k) for k in ("domain", "method", "paired", "trial")}
        layout = layouts.get(spec.get("domain"))
        if layout is not None:
            out["condition"] = (", ".join(f"{k}={_fmt_value(spec.get(k))}" for k in layout.shared_knobs)
                                if layout.shared_knobs else "all")
        return out
    m = CELL_ID.match(cell_id)
    return {k: (int(v) if k in ("paired", "trial") else v) for k, v in m.groupdict().items()} if m else {}


# ---- the job --------------------------------------------------------------------------------------

def deduplicate(rows: pd.DataFrame) -> tuple[pd.DataFrame, list[str]]:
    if "cell_id" not in rows:
        return rows, []
    dup = rows["cell_id"].duplicated(keep="first")
    if not dup.any():
        return rows, []
    ids = rows.loc[dup, "cell_id"].unique()
    return rows[~dup].reset_index(drop=True), [f"{dup.sum()} duplicate row(s) of {len(ids)} cell id(s) "
                                               f"(e.g. {ids[0]}) were dropped; the first copy is kept"]


def compute(rows: pd.DataFrame, cfg: StatsConfig | None = None, inputs: Inputs | None = None) -> StatsResult:
    """All statistics tables for a DataFrame of result rows (one or several domains and sweeps)."""
    cfg = cfg or StatsConfig()
    if cfg.metric not in rows:
        raise SpecError(f"metric column {cfg.metric!r} is not in the rows; choose an eval_* column")
    rows, notes = deduplicate(rows)
    failed = rows[cfg.metric].isna()
    if failed.any():
        notes.append(f"{int(failed.sum())} row(s) have no {cfg.metric} value and are left out")
        rows = rows[~failed]
    if rows.empty:
        raise SpecError("no rows with a metric value to analyse")
    layouts, labelled = {}, []
    parts = {k: [] for k in ("summary", "tests", "pairwise", "by_paired", "efficiency", "claim_2n", "knob_trend")}
    for domain, g in rows.groupby("domain", sort=True):
        layout = domain_layout(g, cfg.metric)
        layouts[domain] = layout
        g = label_rows(g, layout, cfg.metric)
        labelled.append(g)
        summary = summary_table(g, cfg, layout)
        parts["summary"].append(summary)
        omnibus, pairwise = rank_tests(g, cfg, layout)
        parts["tests"].append(pd.DataFrame(omnibus))
        parts["pairwise"].append(pd.DataFrame(pairwise))
        parts["by_paired"].append(pd.DataFrame(by_paired_table(g, cfg, layout)))
        eff, claim = efficiency_tables(g, summary, cfg, layout)
        parts["efficiency"].append(pd.DataFrame(eff))
        parts["claim_2n"].append(pd.DataFrame(claim))
        parts["knob_trend"].append(pd.DataFrame(knob_trends(g, cfg, layout)))
    all_rows = pd.concat(labelled, ignore_index=True)
    tables = {name: (pd.concat([p for p in dfs if not p.empty], ignore_index=True) if any(not p.empty for p in dfs)
                     else pd.DataFrame()) for name, dfs in parts.items()}
    tables["missing"], more = completeness(all_rows, inputs, layouts)
    notes = more + notes
    grid_known = bool(inputs and inputs.sweep_dirs
                      and all(read_manifest_ids(d) is not None for d in inputs.sweep_dirs)
                      and all(any(d.resolve() / "cells" in f.parents for d in inputs.sweep_dirs) for f in inputs.files))
    return StatsResult(cfg, all_rows, layouts, tables, inputs, notes, grid_known)


def run_stats(paths: Sequence[str | Path], cfg: StatsConfig | None = None) -> StatsResult:
    inputs = open_inputs(paths)
    return compute(load_rows(inputs), cfg, inputs)


# ---- writing --------------------------------------------------------------------------------------

def format_cell(v: Any, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "–"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.{digits - 1}e}"
        return f"{v:.{digits}g}"
    return str(v).replace("|", "\\|").replace("\n", " ")


def to_markdown(df: pd.DataFrame, columns: Sequence[str] | None = None) -> str:
    """A GitHub Markdown table (no extra dependency)."""
    if df is None or df.empty:
        return "_(none)_\n"
    cols = [c for c in (columns or df.columns) if c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for rec in df[cols].itertuples(index=False, name=None):
        lines.append("| " + " | ".join(format_cell(v) for v in rec) + " |")
    return "\n".join(lines) + "\n"


def write_tables(result: StatsResult, out_dir: str | Path) -> dict[str, Path]:
    """Every table as stats/<name>.parquet and stats/<name>.md."""
    out = Path(out_dir) / "stats"
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, df in result.tables.items():
        table = pa.Table.from_pandas(df.astype({c: "string" for c in df.columns if df[c].dtype == object}),
                                     preserve_index=False)
        tmp = out / f".{name}.parquet.tmp"
        pq.write_table(table, tmp)
        tmp.replace(out / f"{name}.parquet")
        (out / f"{name}.md").write_text(to_markdown(df))
        written[name] = out / f"{name}.parquet"
    return written
