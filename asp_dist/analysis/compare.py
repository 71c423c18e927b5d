"""Are two runs of the same grid equivalent? `asp-dist compare A B` (and bench/compare_grids.py).

A and B are sweeps (a directory or a name under --results) or .parquet files of rows. Only trials
present in both are compared. Per group (domain, method, paired and any --by columns):

- the median of A and of B over trials, each with a percentile-bootstrap 95 % interval;
- `a_in_b` / `b_in_a`: whether each median lies inside the other run's interval;
- the median of the per-trial differences A − B (rows paired by block: the same root_seed and trial
  within the group) and its bootstrap interval; `diff_ci_has_0`: whether that interval contains 0;
- with a margin M: `within_margin`, whether that interval lies inside [−M, M] (M in metric units, or
  a percentage of |B's median| per group, e.g. "5%").

The two runs are *equivalent* when every group has both medians inside the other's interval, no
group is present in only one run, and, when a margin is given, every difference interval lies within
it. Every interval resamples with the same seed (as bench/compare_grids.py always did, so that its
recorded outputs in docs/performance.md reproduce).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd

from asp_dist.analysis.layout import fmt_value
from asp_dist.analysis.markdown import to_markdown
from asp_dist.analysis.rank_tests import bootstrap_median_ci
from asp_dist.errors import SpecError
from asp_dist.results import store
from asp_dist.results.query import load_rows

BASE_KEYS = ("method", "paired")


@dataclass
class Margin:
    """The largest per-trial difference still called equivalent: absolute, or relative to |B's median|."""

    value: float
    relative: bool = False

    def at(self, median_b: float) -> float:
        return self.value * abs(median_b) if self.relative else self.value

    def __str__(self) -> str:
        return f"{self.value * 100:g} % of |B's median|" if self.relative else f"{self.value:g}"


def parse_margin(text: str) -> Margin:
    """'0.01' (metric units) or '5%' (of |B's median| per group); refused unless finite and >= 0."""
    raw = text.strip()
    relative = raw.endswith("%")
    try:
        value = float(raw.removesuffix("%"))
    except ValueError:
        raise SpecError(f"--margin {text!r}: write a number in metric units (0.01) or a percentage (5%)") from None
    if not np.isfinite(value) or value < 0:
        raise SpecError(f"--margin {text!r} must be a finite number >= 0")
    return Margin(value / 100 if relative else value, relative)


def load(path: str, results: str = store.DEFAULT_RESULTS) -> pd.DataFrame:
    """The rows of a sweep directory or name, a directory of Parquet files, or a .parquet file."""
    rows = load_rows([path], results)
    for col in ("domain", "method"):
        rows[col] = rows[col].astype(str)
    if "root_seed" not in rows:
        rows["root_seed"] = 0
    rows["root_seed"] = rows["root_seed"].fillna(0)
    return rows


def _paired_diffs(ga: pd.DataFrame, gb: pd.DataFrame, metric: str) -> np.ndarray:
    """A − B per block (root_seed, trial) present in both, in A's order."""
    a = ga.set_index(["root_seed", "trial"])[metric]
    b = gb.set_index(["root_seed", "trial"])[metric]
    return a.sub(b).dropna().to_numpy(float)


def compare(a: pd.DataFrame, b: pd.DataFrame, metric: str, keys: Sequence[str], n_boot: int, seed: int,
            margin: Margin | None = None) -> pd.DataFrame:
    """One row per group of `keys` present in both A and B (trials present in both only)."""
    ci = lambda x: bootstrap_median_ci(x, n_boot=n_boot, seed=seed)  # noqa: E731
    keys = list(keys)
    trials = sorted(set(a["trial"]) & set(b["trial"]))
    a, b = a[a["trial"].isin(trials)], b[b["trial"].isin(trials)]
    groups_b = {key: g for key, g in b.groupby(keys, sort=True)}
    out = []
    for key, ga in a.groupby(keys, sort=True):
        if key not in groups_b:
            continue
        gb = groups_b[key]
        xa, xb = ga[metric].to_numpy(float), gb[metric].to_numpy(float)
        lo_a, hi_a = ci(xa)
        lo_b, hi_b = ci(xb)
        diffs = _paired_diffs(ga, gb, metric)
        lo_d, hi_d = ci(diffs)
        med_a, med_b = float(np.median(xa)), float(np.median(xb))
        rec = {**dict(zip(keys, key if isinstance(key, tuple) else (key,))), "n_a": len(xa), "n_b": len(xb),
               "median_a": med_a, "ci_a": f"{lo_a:.4g}–{hi_a:.4g}", "median_b": med_b, "ci_b": f"{lo_b:.4g}–{hi_b:.4g}",
               "a_in_b": lo_b <= med_a <= hi_b, "b_in_a": lo_a <= med_b <= hi_a,
               "overlap": max(lo_a, lo_b) <= min(hi_a, hi_b),
               "median_diff": float(np.median(diffs)) if len(diffs) else np.nan,
               "diff_ci": f"{lo_d:.4g}–{hi_d:.4g}", "diff_ci_has_0": bool(lo_d <= 0 <= hi_d)}
        if margin is not None:
            m = margin.at(med_b)
            rec["margin"] = m
            rec["within_margin"] = bool(-m <= lo_d and hi_d <= m)
        out.append(rec)
    return pd.DataFrame(out)


def unmatched_groups(a: pd.DataFrame, b: pd.DataFrame, keys: Sequence[str]) -> tuple[list, list]:
    """Groups (over the trials in both) present only in A, and only in B."""
    trials = set(a["trial"]) & set(b["trial"])
    ka = {k for k, _ in a[a["trial"].isin(trials)].groupby(list(keys))}
    kb = {k for k, _ in b[b["trial"].isin(trials)].groupby(list(keys))}
    return sorted(ka - kb, key=str), sorted(kb - ka, key=str)


def counts_line(table: pd.DataFrame) -> str:
    """bench/compare_grids.py's summary line (docs/performance.md records it)."""
    return (f"groups: {len(table)}; intervals overlap in {int(table['overlap'].sum())}; A's median inside B's "
            f"interval in {int(table['a_in_b'].sum())}, B's inside A's in {int(table['b_in_a'].sum())}; interval "
            f"of the median per-trial difference contains 0 in {int(table['diff_ci_has_0'].sum())}")


def verdict(table: pd.DataFrame, only_a: list, only_b: list, margin: Margin | None) -> tuple[bool, str]:
    """(equivalent?, the verdict line)."""
    inside = table["a_in_b"] & table["b_in_a"]
    reasons = []
    if not inside.all():
        reasons.append(f"{int((~inside).sum())} of {len(table)} group(s) have a median outside the other's interval")
    if margin is not None and not table["within_margin"].all():
        reasons.append(f"{int((~table['within_margin']).sum())} of {len(table)} group(s) have a difference interval "
                       f"beyond the margin ±{margin}")
    if only_a or only_b:
        reasons.append(f"{len(only_a)} group(s) only in A and {len(only_b)} only in B")
    if reasons:
        return False, "verdict: NOT equivalent: " + "; ".join(reasons)
    tail = f", and every difference interval within ±{margin}" if margin is not None else ""
    return True, (f"verdict: equivalent: in all {len(table)} groups each median lies inside the other run's 95 % "
                  f"interval{tail}")


@dataclass
class Comparison:
    header: str
    table: pd.DataFrame
    only_a: list
    only_b: list
    equivalent: bool
    verdict: str

    def text(self, markdown: bool = False) -> str:
        shown = to_markdown(self.table).rstrip() if markdown else self.table.to_string(index=False)
        lines = [self.header, shown, counts_line(self.table)]
        if self.only_a or self.only_b:
            lines.append(f"groups only in A: {', '.join(map(str, self.only_a[:10])) or 'none'}; "
                         f"only in B: {', '.join(map(str, self.only_b[:10])) or 'none'}")
        return "\n".join(lines + [self.verdict])


def run_compare(path_a: str, path_b: str, domain: str | None = None, metric: str = "eval_mixed",
                by: Sequence[str] = (), margin: Margin | None = None, n_boot: int = 5000, seed: int = 0,
                results: str = store.DEFAULT_RESULTS) -> Comparison:
    """Load A and B, check the request, compare them group by group and decide."""
    a, b = load(path_a, results), load(path_b, results)
    if domain is not None:
        a, b = a[a["domain"] == domain], b[b["domain"] == domain]
        if a.empty or b.empty:
            raise SpecError(f"no {domain} rows in {'A' if a.empty else 'B'} ({path_a if a.empty else path_b})")
    for col in [metric, *by]:
        for name, rows in (("A", a), ("B", b)):
            if col not in rows:
                raise SpecError(f"column {col!r} is not in {name} ({path_a if name == 'A' else path_b})")
    for col in by:
        if a[col].isna().any() or b[col].isna().any():  # e.g. a knob of one domain only: a group of its own
            a, b = (rows.assign(**{col: [fmt_value(v) if pd.notna(v) else "–" for v in rows[col]]}) for rows in (a, b))
    trials = sorted(set(a["trial"]) & set(b["trial"]))
    if not trials:
        raise SpecError("A and B have no trial in common; nothing to compare")
    keys = ([] if domain is not None else ["domain"]) + list(BASE_KEYS) + list(by)
    table = compare(a, b, metric, keys, n_boot, seed, margin)
    if table.empty:
        raise SpecError("A and B have no group (" + ", ".join(keys) + ") in common; nothing to compare")
    only_a, only_b = unmatched_groups(a, b, keys)
    what = domain if domain is not None else ", ".join(sorted(set(a["domain"]) | set(b["domain"])))
    header = (f"{what}, {metric}: A = {path_a} ({len(a)} rows), B = {path_b} ({len(b)} rows); "
              f"{len(trials)} trials in both; bootstrap {n_boot}, seed {seed}")
    ok, line = verdict(table, only_a, only_b, margin)
    return Comparison(header, table, only_a, only_b, ok, line)
