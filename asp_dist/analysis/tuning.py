"""The report's tuning section: what `asp-dist tune` tried, read from each input tune run's configurations.parquet.

Per method: its best configuration, the spread of the objective over every configuration it tried (how much
its knobs matter), and the objective against the configuration index with the best so far (does the search
converge within the budget?). A run with ASHA (`scheduler = "asha"`) has configurations it stopped early: they
have no objective, are counted per method (`stopped_early`) and never chosen. Only runs of `asp-dist tune` have
a configurations.parquet; a sweep has none, and then the report has no tuning section.

Beside them: the expected best objective against the budget (Dodge et al. 2019, "Show your work", EMNLP: the
best of n configurations drawn from those tried, n = 1 … N), every configuration's values, and, where the run
validated its top configurations on held-out trials (configurations.parquet's `stage` column: "search" and
"validation"), which one the validation chose. A file written before that column has only the search: every row
counts as "search", and the search's tables read only those rows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from asp_dist.analysis.document import Block, Heading, Table, Text
from asp_dist.analysis.job import read_tune_run
from asp_dist.analysis.markdown import format_value
from asp_dist.results.location import as_path
from asp_dist.sweep.tune_plan import winning_configuration


def read_configurations(result) -> pd.DataFrame:
    """Every configuration of the input tune runs (columns of configurations.parquet, plus run, domain and
    higher_is_better); empty when no input is a tune run."""
    frames = []
    for sweep_dir in (result.inputs.sweep_dirs if result.inputs is not None else []):
        found = read_tune_run(sweep_dir)
        if found is None:
            continue
        table, domain, _ = found
        layout = result.layouts.get(domain)
        higher = layout.higher_is_better if layout is not None else True
        frames.append(table.assign(run=as_path(sweep_dir).name, domain=domain, higher_is_better=higher))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


SEARCH, VALIDATION = "search", "validation"  # the stages of configurations.parquet's `stage` column


def _stage(configs: pd.DataFrame) -> pd.Series:
    """Each row's stage; a file written before the validation stage has no `stage` column: all "search"."""
    if "stage" not in configs:
        return pd.Series(SEARCH, index=configs.index)
    return configs["stage"].astype(object).where(configs["stage"].notna(), SEARCH)


def search_rows(configs: pd.DataFrame) -> pd.DataFrame:
    """The search stage's rows: those the tables of the search speak of (a file without stages: all of them)."""
    return configs if "stage" not in configs else configs[_stage(configs).eq(SEARCH)]


def _scored(configs: pd.DataFrame) -> pd.DataFrame:
    """The search's configurations, with no objective where ASHA stopped them (configurations.parquet has none
    there)."""
    configs = search_rows(configs)
    if "stopped_early" not in configs:
        return configs
    return configs.assign(objective=configs["objective"].where(~configs["stopped_early"].eq(True)))


def _knob_columns(configs: pd.DataFrame) -> list[str]:
    return [c for c in configs.columns if c.startswith("knob_")]


def best_table(configs: pd.DataFrame) -> pd.DataFrame:
    """Each (run, method) of the search: its best configuration (ties: the lower index), its values and objective, and
    configuration 0's objective (the method's defaults where the run started from them); where a run used ASHA,
    how many configurations it stopped early (never chosen: they have no objective)."""
    rows = []
    asha = "stopped_early" in configs
    for (run, method), g in _scored(configs).groupby(["run", "method"], sort=False):
        scored = g[g["objective"].notna()].sort_values("configuration")
        best = winning_configuration(g, bool(g["higher_is_better"].iloc[0]))
        if best is None:
            continue
        values = ", ".join(f"{c[5:]}={_short(best[c])}" for c in _knob_columns(g) if pd.notna(best[c]))
        first = scored[scored["configuration"] == 0]
        rows.append({"run": run, "method": method, "configurations": len(g), "best_configuration": int(best["configuration"]),
                     "best_objective": float(best["objective"]),
                     "configuration_0": float(first["objective"].iloc[0]) if len(first) else np.nan,
                     **({"stopped_early": int(g["stopped_early"].eq(True).sum())} if asha else {}),
                     "values": values})
    return pd.DataFrame(rows)


def spread_table(configs: pd.DataFrame) -> pd.DataFrame:
    """The objective over each method's search configurations: quartiles and range (sensitivity to its knobs), and
    the index at which the best so far was last improved (late improvements: the budget was not enough)."""
    rows = []
    for (run, method), g in _scored(configs).groupby(["run", "method"], sort=False):
        g = g.sort_values("configuration")
        y = g["objective"].to_numpy(dtype=float)
        ok = ~np.isnan(y)
        if not ok.any():
            continue
        higher = bool(g["higher_is_better"].iloc[0])
        best_so_far = _best_so_far(y, higher)
        last_gain = int(g["configuration"].to_numpy()[np.flatnonzero(np.diff(best_so_far, prepend=np.nan) != 0)[-1]]) \
            if len(y) else 0
        q1, med, q3 = np.nanpercentile(y, [25, 50, 75])
        rows.append({"run": run, "method": method, "n": int(ok.sum()), "min": float(np.nanmin(y)), "q1": float(q1),
                     "median": float(med), "q3": float(q3), "max": float(np.nanmax(y)),
                     "last_improved_at": last_gain})
    return pd.DataFrame(rows)


def _best_so_far(y: np.ndarray, higher: bool) -> np.ndarray:
    filled = np.where(np.isnan(y), -np.inf if higher else np.inf, y)
    out = np.maximum.accumulate(filled) if higher else np.minimum.accumulate(filled)
    return np.where(np.isinf(out), np.nan, out)


def _short(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def plot_tuning(configs: pd.DataFrame, out_dir: Path) -> list:
    """One figure per tune run: each method's objective by configuration index (dots) and its best so far (line),
    over the search."""
    if configs.empty:
        return []
    import matplotlib.pyplot as plt

    from asp_dist.analysis.plots import METHOD_COLORS, Figure, save_figure

    figures = []
    for run, runs in _scored(configs).groupby("run", sort=False):
        higher = bool(runs["higher_is_better"].iloc[0])
        fig, ax = plt.subplots(figsize=(6.4, 3.6), layout="constrained")
        for i, (method, g) in enumerate(runs.groupby("method", sort=False)):
            g = g.sort_values("configuration")
            color = METHOD_COLORS.get(method, f"C{i}")
            ax.plot(g["configuration"], g["objective"], "o", color=color, alpha=0.45, markersize=4)
            ax.plot(g["configuration"], _best_so_far(g["objective"].to_numpy(dtype=float), higher), "-", color=color,
                    drawstyle="steps-post", label=f"{method.upper()} (best so far)")
        ax.set_xlabel("configuration (0: the method's defaults)")
        ax.set_ylabel(f"objective ({'↑ higher' if higher else '↓ lower'} is better)")
        ax.set_title(f"{run}: the search of each method")
        ax.legend(fontsize=8)
        stem = f"tuning_{run}"
        figures.append(Figure(stem, f"{run}: objective by configuration",
                              "Each method's objective (median of the metric over its calibration cells) for every "
                              "configuration tried, and the best so far.", save_figure(fig, out_dir, stem)))
    return figures


# ---- expected best objective against the budget ------------------------------------------------------------
def expected_best(values, higher_is_better: bool = True) -> pd.DataFrame:
    """The expected best of n configurations drawn with replacement from `values` (one method's objectives, NaN
    left out), for n = 1 … N, and its standard deviation (Dodge et al. 2019, "Show your work: improved reporting of
    experimental results", EMNLP).

    With v_(1), …, v_(N) ordered from worst to best (ascending where higher is better, descending where lower is),
    the best of n draws is v_(i) with probability p_i = (i/N)^n − ((i−1)/N)^n, so E[best_n] = Σ_i p_i·v_(i) and
    Var = Σ_i p_i·(v_(i) − E)². n = 1 gives the mean of the values, n → ∞ the best of them. Columns n, mean, sd;
    no rows when no value is left."""
    v = np.asarray(values, dtype=float).ravel()
    v = np.sort(v[~np.isnan(v)])
    if not higher_is_better:
        v = v[::-1]  # worst first, whichever way the objective points
    big_n = len(v)
    if big_n == 0:
        return pd.DataFrame({"n": np.array([], dtype=int), "mean": np.array([]), "sd": np.array([])})
    n = np.arange(1, big_n + 1)[:, None]
    i = np.arange(1, big_n + 1)[None, :]
    p = (i / big_n) ** n - ((i - 1) / big_n) ** n  # row n: the law of the best of n draws over v
    mean = p @ v
    var = (p * (v[None, :] - mean[:, None]) ** 2).sum(axis=1)  # about the mean: no cancellation of large squares
    return pd.DataFrame({"n": n.ravel(), "mean": mean, "sd": np.sqrt(np.maximum(var, 0.0))})


def _budget_values(g: pd.DataFrame) -> tuple[np.ndarray, int]:
    """One method's search objectives for the expected best, and how many of them are ASHA's: a stopped
    configuration counts at `objective_at_stop`, the intermediate objective ASHA judged it by."""
    y = g["objective"].to_numpy(dtype=float).copy()
    if "stopped_early" not in g:
        return y, 0
    stopped = g["stopped_early"].eq(True).to_numpy()
    at_stop = g["objective_at_stop"].to_numpy(dtype=float) if "objective_at_stop" in g else np.full(len(g), np.nan)
    y[stopped] = at_stop[stopped]
    return y, int((stopped & ~np.isnan(at_stop)).sum())


def expected_best_table(configs: pd.DataFrame) -> pd.DataFrame:
    """Each (run, method) of the search: expected_best of its objectives, n = 1 … N (rows n, mean, sd), with N
    (`configurations`: those with a value) and, where the run used ASHA, how many of them count at their stop
    (`at_stop`). A method with no value is left out."""
    frames = []
    search = search_rows(configs)
    asha = "stopped_early" in search
    for (run, method), g in search.groupby(["run", "method"], sort=False):
        higher = bool(g["higher_is_better"].iloc[0])
        values, at_stop = _budget_values(g)
        curve = expected_best(values, higher)
        if curve.empty:
            continue
        frames.append(curve.assign(run=run, method=method, higher_is_better=higher, configurations=len(curve),
                                   **({"at_stop": at_stop} if asha else {})))
    if not frames:
        return pd.DataFrame()
    out = pd.concat(frames, ignore_index=True)
    first = ["run", "method", "configurations", *(["at_stop"] if asha else []), "n", "mean", "sd"]
    return out[first + [c for c in out.columns if c not in first]]


def expected_best_summary(configs: pd.DataFrame) -> pd.DataFrame:
    """expected_best_table, one row per (run, method): mean ± sd at n = 1, 2, 4, … below N and at N, and the
    share of the rise from n = 1 to n = N that the second half of the budget brought (`gain after N/2`: near 0,
    the curve had flattened; large, more configurations would likely still have helped)."""
    table = expected_best_table(configs)
    if table.empty:
        return table
    top = int(table["configurations"].max())
    powers = [2 ** k for k in range(int(np.log2(top)) + 1) if 2 ** k < top]
    rows = []
    for (run, method), g in table.groupby(["run", "method"], sort=False):
        at = g.set_index("n")
        big_n = int(g["configurations"].iloc[0])
        row = {"run": run, "method": method, "configurations": big_n}
        if "at_stop" in g:
            row["at_stop"] = int(g["at_stop"].iloc[0])
        for n in powers:
            row[f"n={n}"] = _mean_sd(at.loc[n]) if n < big_n else "–"
        row["n=N"] = _mean_sd(at.loc[big_n])
        rise = at.loc[big_n, "mean"] - at.loc[1, "mean"]
        late = at.loc[big_n, "mean"] - at.loc[max(1, big_n // 2), "mean"]
        row["gain after N/2"] = f"{100 * late / rise:.0f} %" if rise != 0 else "–"  # sign-free: both flip together
        rows.append(row)
    return pd.DataFrame(rows)


def _mean_sd(point: pd.Series) -> str:
    return f"{format_value(float(point['mean']))} ± {format_value(float(point['sd']), 2)}"


def plot_expected_best(configs: pd.DataFrame, out_dir: Path) -> list:
    """One figure, a panel per tune run: each method's expected best objective against the configurations tried,
    with a band of ±1 sd (expected_best_table); nothing when no method has a value."""
    if configs.empty:  # no input is a tune run
        return []
    table = expected_best_table(configs)
    if table.empty:
        return []
    import matplotlib.pyplot as plt

    from asp_dist.analysis.plots import METHOD_COLORS, Figure, save_figure

    runs = list(dict.fromkeys(table["run"]))
    fig, axes = plt.subplots(1, len(runs), figsize=(max(6.4, 4.4 * len(runs)), 3.6), squeeze=False,
                             layout="constrained")
    for ax, run in zip(axes[0], runs):
        g_run = table[table["run"] == run]
        higher = bool(g_run["higher_is_better"].iloc[0])
        for i, (method, g) in enumerate(g_run.groupby("method", sort=False)):
            color = METHOD_COLORS.get(method, f"C{i}")
            x, y, sd = g["n"].to_numpy(), g["mean"].to_numpy(), g["sd"].to_numpy()
            ax.plot(x, y, "-", color=color, label=method.upper())
            ax.fill_between(x, y - sd, y + sd, color=color, alpha=0.15, linewidth=0)
        ax.set_xlabel("configurations tried (n)")
        ax.set_ylabel(f"expected best objective\n({'↑ higher' if higher else '↓ lower'} is better)")
        ax.set_title(f"{run}: expected best against the budget", fontsize=10)
        ax.legend(fontsize=8)
    stem = "tuning_expected_best"
    stopped = "at_stop" in table and table["at_stop"].gt(0).any()
    caption = ("The best objective a search of n configurations drawn at random from those each method tried "
               "would be expected to find (Dodge et al. 2019), ±1 sd. A curve that flattens well before the last "
               "configuration says the method's budget was enough; one still rising at the end says more "
               "configurations would likely have found a better one."
               + (" Configurations ASHA stopped count at the objective it stopped them at (`objective_at_stop`)."
                  if stopped else ""))
    return [Figure(stem, "Expected best objective against the tuning budget", caption,
                   save_figure(fig, out_dir, stem))]


# ---- validation on held-out trials, and every configuration's values -----------------------------------------
def _flag(rows: pd.DataFrame, column: str) -> pd.Series:
    return rows[column].eq(True) if column in rows else pd.Series(False, index=rows.index)


def validation_tables(configs: pd.DataFrame) -> list[tuple[str, str, str, pd.DataFrame]]:
    """Each (run, method) with validation rows: a line saying which configuration the validation chose and
    whether the method's default won, and a table of every validated configuration (its index, or "default"),
    its search objective (its row's `search_objective`, else the search row of the same index, or for a default
    without one the search's default row) and its validation objective. Nothing for a file without a validation
    stage."""
    if "stage" not in configs:
        return []
    stage = _stage(configs)
    search, validated = _scored(configs), configs[stage.eq(VALIDATION)]
    out = []
    for (run, method), g in validated.groupby(["run", "method"], sort=False):
        found = search[(search["run"] == run) & (search["method"] == method)]
        by_index = found.dropna(subset=["configuration"]).drop_duplicates("configuration").set_index("configuration")
        default_search = found[_flag(found, "default")]
        rows = []
        for rec, is_default, chosen in zip(g.to_dict("records"), _flag(g, "default"), _flag(g, "chosen")):
            index = rec.get("configuration")
            has_index = index is not None and not pd.isna(index)
            if pd.notna(rec.get("search_objective", np.nan)):  # the validation row's own copy, where it has one
                before = rec["search_objective"]
            elif has_index and int(index) in by_index.index:
                before = by_index.loc[int(index), "objective"]
            elif is_default and len(default_search):
                before = default_search["objective"].iloc[0]
            else:
                before = np.nan
            label = (f"{int(index)} (default)" if has_index else "default") if is_default else \
                (str(int(index)) if has_index else "–")
            rows.append({"configuration": label, "search_objective": float(before),
                         "validation_objective": float(rec["objective"]), "chosen": "✓" if chosen else ""})
        table = pd.DataFrame(rows)
        picks = [r["configuration"] for r in rows if r["chosen"]]
        default_won = bool((_flag(g, "default") & _flag(g, "chosen")).any())
        pick = "" if not picks else "the default" if picks[0] == "default" else f"configuration {picks[0]}"
        line = (f"**{run}, {method.upper()}**: the validation chose {pick}; "
                + ("the default won." if default_won else
                   "the default did not win." if _flag(g, "default").any() else "the default was not validated.")
                if picks else f"**{run}, {method.upper()}**: the validation chose no configuration.")
        out.append((run, method, line, table))
    return out


def configuration_tables(configs: pd.DataFrame) -> list[tuple[str, str, pd.DataFrame]]:
    """Each (run, method) of the search: one row per configuration, its index, the value of each knob the method
    searched (short names) and its objective; where the run used ASHA, the curve point a stopped one was stopped
    at and its objective there. The report's tables round the values."""
    out = []
    for (run, method), g in _scored(configs).groupby(["run", "method"], sort=False):
        g = g.sort_values("configuration")
        knobs = [c for c in _knob_columns(g) if g[c].notna().any()]
        table = pd.DataFrame({"configuration": g["configuration"].astype(int).to_numpy()})
        for c in knobs:
            table[c[5:]] = g[c].to_numpy()
        table["objective"] = g["objective"].to_numpy(dtype=float)
        if "stopped_early" in g:
            at = g["objective_at_stop"] if "objective_at_stop" in g else pd.Series(np.nan, index=g.index)
            point = g["stopped_at_point"] if "stopped_at_point" in g else pd.Series(pd.NA, index=g.index)
            table["stopped"] = [f"at point {_point(p)}: {format_value(float(v))}" if s else ""
                                for s, p, v in zip(g["stopped_early"].eq(True), point, at)]
        out.append((run, method, table))
    return out


def _point(p) -> str:
    return "?" if p is None or pd.isna(p) else str(int(p))


def tuning_blocks(configs: pd.DataFrame) -> list[Block]:
    """The report's section, or nothing when no input is a tune run."""
    if configs.empty:
        return []
    search = search_rows(configs)
    blocks: list[Block] = [
        Heading(2, "Tuning: every method on the same budget"),
        Text("Each method's best configuration by its own objective (the median of the metric over its "
             "calibration cells), beside configuration 0 (its defaults, where the run started from them):"),
        Table(best_table(configs)),
        *([Text("`stopped_early`: the configurations ASHA stopped on their learning curves; they have no "
                "objective and are never chosen (configurations.parquet has the curve point each was stopped "
                "at and its objective there).")]
          if "stopped_early" in search and search["stopped_early"].eq(True).any() else []),
        Text("The objective over every configuration a method tried: its spread says how much the method's "
             "knobs matter; `last_improved_at` is the configuration that last raised the best so far (near the "
             "budget's end: the search had not settled). The figure `tuning_<run>` plots it."),
        Table(spread_table(configs))]
    validated = validation_tables(configs)
    if validated:
        blocks += [Heading(3, "Validation on held-out trials"),
                   Text("The top configurations of each method's search and its default, trained again on held-out "
                        "trials: each one's objective in the search and in the validation, and the one chosen.")]
        for _, _, line, table in validated:
            blocks += [Text(line), Table(table)]
    summary = expected_best_summary(configs)
    if not summary.empty:
        stopped = "at_stop" in summary and summary["at_stop"].gt(0).any()
        blocks += [Heading(3, "Expected best objective against the budget"),
                   Text("The best objective a search of n configurations drawn at random (with replacement) from "
                        "the N a method tried would be expected to find, mean ± sd (Dodge et al. 2019, *Show your "
                        "work*, EMNLP): a curve that flattens well before n = N says the budget was enough. `gain "
                        "after N/2`: the share of the rise from n = 1 to n = N that the budget's second half "
                        "brought (large: more configurations would likely still have helped). The figure "
                        "`tuning_expected_best` plots it."
                        + (" Configurations ASHA stopped count at `objective_at_stop`, the intermediate objective "
                           "it stopped them at (`at_stop`: how many), not at a final one." if stopped else "")),
                   Table(summary)]
    blocks += [Heading(3, "Every configuration tried"),
               Text("The values of the knobs each method searched, per configuration (0: the method's defaults, "
                    "where the run started from them), and its objective"
                    + ("; `stopped`: the curve point where ASHA stopped it and its objective there."
                       if "stopped_early" in search else "."))]
    for run, method, table in configuration_tables(configs):
        blocks += [Text(f"**{run}, {method.upper()}**: configurations {_index_range(table['configuration'])}"),
                   Table(table)]
    return blocks


def _index_range(index: pd.Series) -> str:
    """`0–23` for contiguous indices, else the count and the range."""
    lo, hi = int(index.min()), int(index.max())
    return f"{lo}–{hi}" if hi - lo + 1 == index.nunique() else f"{index.nunique()} of {lo}–{hi}"


def tune_grid(configs: pd.DataFrame, domain: str) -> tuple[set[str], set[str], str]:
    """What the report's "What was run" says of a domain's tune runs instead of every searched value: the cell ids
    its configurations trained (either stage), the knobs searched, and the configurations named by method and
    index (`pc: configurations 0–23 (tuning section)`). Empty sets and "" where the domain has no tune run."""
    if configs.empty or "domain" not in configs:
        return set(), set(), ""
    mine = configs[configs["domain"] == domain]
    if mine.empty:
        return set(), set(), ""
    cells = {c for ids in mine["cell_ids"].dropna() for c in str(ids).split(",") if c} if "cell_ids" in mine else set()
    knobs = {c[5:] for c in _knob_columns(mine) if mine[c].notna().any()}
    several = mine["run"].nunique() > 1
    stage = _stage(mine)
    parts = []
    for (run, method), g in search_rows(mine).groupby(["run", "method"], sort=False):
        checked = int((stage.eq(VALIDATION) & mine["run"].eq(run) & mine["method"].eq(method)).sum())
        parts.append(f"{f'{run} ' if several else ''}{method}: configurations {_index_range(g['configuration'])}"
                     + (f" (+{checked} validated)" if checked else ""))
    return cells, knobs, "; ".join(parts) + " (tuning section)"
