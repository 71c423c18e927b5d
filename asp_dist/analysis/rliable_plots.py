"""Figures of the rliable view (rliable_view.py), drawn from its tables, in the style of plots.py.

- `<domain>_iqm_vs_paired`: the sample-efficiency curve: IQM of the normalised score against the
  paired count per treatment, with its 95 % stratified-bootstrap band, one panel per condition;
- `rliable_aggregate`: IQM of the normalised score pooled over the paired ranges, per treatment,
  over all domains and per domain, with intervals;
- `rliable_profiles`: performance profiles (fraction of runs with normalised score > τ), with bands;
- `rliable_improvement`: P(A > B), unpaired and paired, with intervals, per pair and condition.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from asp_dist.analysis.job import StatsResult
from asp_dist.analysis.layout import condition_key, treatment_order
from asp_dist.analysis.paper import knob_label
from asp_dist.analysis.plots import MAX_PANELS, Figure, _panels, _style, _use_log2, plt, save_figure

NORM_LABEL = "normalised score\n(0 = PC with least paired data, 1 = base pair's self-play)"


def plot_iqm_vs_paired(result: StatsResult, domain: str, out_dir: Path) -> Figure | None:
    table = result.tables.get("iqm", pd.DataFrame())
    s = table[table["domain"] == domain] if not table.empty else table
    if s.empty or s["iqm_norm"].isna().all():
        return None
    conditions = [c for c in sorted(s["condition"].unique(), key=condition_key)
                  if s.loc[s["condition"] == c, "paired"].nunique() >= 2][:MAX_PANELS]
    if not conditions:
        return None
    fig, axes = _panels(len(conditions))
    log2 = _use_log2(s["paired"].to_numpy())
    for ax, cond in zip(axes, conditions):
        sc = s[s["condition"] == cond]
        for i, treat in enumerate(treatment_order(sc["treatment"])):
            g = sc[sc["treatment"] == treat].sort_values("paired")
            style = _style(treat, i)
            ax.plot(g["paired"], g["iqm_norm"], **style)
            ax.fill_between(g["paired"], g["norm_ci_low"], g["norm_ci_high"], color=style["color"], alpha=0.15,
                            linewidth=0)
        if log2:
            ax.set_xscale("symlog", base=2, linthresh=1)
        ticks = sorted(sc["paired"].unique())
        ax.set_xticks(ticks)
        ax.set_xticklabels([str(p) for p in ticks])
        ax.set_xlabel(knob_label(domain, "paired"))
        if cond != "all":
            ax.set_title(cond, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(NORM_LABEL)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{domain}: IQM over trials with 95 % bootstrap band", fontsize=11)
    stem = f"{domain}_iqm_vs_paired"
    return Figure(stem, f"{domain}: sample efficiency (IQM of the normalised score against paired count)",
                  "Interquartile mean over trials per method and paired count, 95 % percentile-bootstrap band; "
                  "the normalisation is in stats/normalisation.md.", save_figure(fig, out_dir, stem))


def _intervals(ax: plt.Axes, labels: list[str], points, lows, highs, colors) -> None:
    y = np.arange(len(labels))[::-1]
    for yi, p, lo, hi, c in zip(y, points, lows, highs, colors):
        ax.plot([lo, hi], [yi, yi], color=c, linewidth=6, alpha=0.35, solid_capstyle="butt")
        ax.plot([p], [yi], marker="|", color=c, markersize=14, markeredgewidth=2)
    ax.set_yticks(y)
    ax.set_yticklabels(labels, fontsize=8)
    ax.grid(alpha=0.3, axis="x")


def _color(treatment: str, i: int) -> str:
    return _style(treatment, i)["color"]


def plot_aggregate(result: StatsResult, out_dir: Path) -> Figure | None:
    agg = result.tables.get("aggregate", pd.DataFrame())
    if agg.empty:
        return None
    scopes = list(dict.fromkeys(agg["scope"]))[:MAX_PANELS]
    fig, axes = _panels(len(scopes))
    for ax, scope in zip(axes, scopes):
        g = agg[agg["scope"] == scope]
        order = treatment_order(g["treatment"])
        g = g.set_index("treatment").loc[order]
        _intervals(ax, [t.upper() if "[" not in t else t for t in order], g["iqm_norm"], g["ci_low"], g["ci_high"],
                   [_color(t, i) for i, t in enumerate(order)])
        ax.set_title(scope, fontsize=10)
        ax.set_xlabel("IQM of the normalised score")
    fig.suptitle("IQM of the normalised score over each domain's paired range (95 % stratified bootstrap)",
                 fontsize=11)
    stem = "rliable_aggregate"
    return Figure(stem, "Aggregate: IQM of the normalised score",
                  "Runs pooled over the tasks (domain, condition, paired count) of each domain's paired range; "
                  "the interval resamples trials within every task.", save_figure(fig, out_dir, stem))


def plot_profiles(result: StatsResult, out_dir: Path) -> Figure | None:
    prof = result.tables.get("profiles", pd.DataFrame())
    if prof.empty:
        return None
    scopes = list(dict.fromkeys(prof["scope"]))[:MAX_PANELS]
    fig, axes = _panels(len(scopes))
    for ax, scope in zip(axes, scopes):
        g = prof[prof["scope"] == scope]
        for i, treat in enumerate(treatment_order(g["treatment"])):
            t = g[g["treatment"] == treat]
            style = _style(treat, i)
            style["marker"] = None
            ax.plot(t["tau"], t["fraction"], **style)
            ax.fill_between(t["tau"], t["ci_low"], t["ci_high"], color=style["color"], alpha=0.15, linewidth=0)
        ax.set_title(scope, fontsize=10)
        ax.set_xlabel("normalised score τ")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("fraction of runs with score > τ")
    axes[0].legend(fontsize=8)
    fig.suptitle("Performance profiles over each domain's paired range (95 % stratified-bootstrap band)",
                 fontsize=11)
    stem = "rliable_profiles"
    return Figure(stem, "Performance profiles of the normalised score",
                  "Fraction of runs whose normalised score exceeds τ; 0 = PC with the least paired data, "
                  "1 = the base pair's own self-play.", save_figure(fig, out_dir, stem))


def plot_improvement(result: StatsResult, out_dir: Path) -> Figure | None:
    imp = result.tables.get("improvement", pd.DataFrame())
    if imp.empty:
        return None
    imp = imp.head(40)  # a readable figure; every pair is in stats/improvement.md
    labels = [f"{d} {c if c != 'all' else ''}: P({a.upper()} > {b.upper()})".replace("  ", " ")
              for d, c, a, b in zip(imp["domain"], imp["condition"], imp["a"], imp["b"])]
    fig, axes = plt.subplots(1, 2, figsize=(11, 0.32 * len(imp) + 1.4), sharey=True, squeeze=False,
                             layout="constrained")
    for ax, (col, title) in zip(axes[0], (("poi", "unpaired (runs)"), ("poi_paired", "paired (blocks)"))):
        colors = [_color(a, 0) for a in imp["a"]]
        _intervals(ax, labels, imp[col], imp[f"{col}_ci_low"], imp[f"{col}_ci_high"], colors)
        ax.axvline(0.5, color="black", linewidth=0.8)
        ax.set_xlim(-0.02, 1.02)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("probability of improvement")
    fig.suptitle("P(A > B) over each condition's paired range (95 % stratified bootstrap)", fontsize=11)
    stem = "rliable_improvement"
    return Figure(stem, "Probability of improvement",
                  "Unpaired: P(X > Y) + ½ P(X = Y) over runs of the same task, averaged over tasks (rliable). "
                  "Paired: the same over blocks (same base, data and initial weights).", save_figure(fig, out_dir, stem))


def plot_rliable(result: StatsResult, out_dir: str | Path) -> list[Figure]:
    """Every figure of the rliable view the tables support, under `out_dir` (…/figures)."""
    out = Path(out_dir)
    figures = [plot_iqm_vs_paired(result, domain, out) for domain in sorted(result.layouts)]
    figures += [plot_aggregate(result, out), plot_profiles(result, out), plot_improvement(result, out)]
    return [f for f in figures if f is not None]
