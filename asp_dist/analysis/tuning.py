"""The report's tuning section: what `asp-dist tune` tried, read from each input tune run's configurations.parquet.

Per method: its best configuration, the spread of the objective over every configuration it tried (how much
its knobs matter), and the objective against the configuration index with the best so far (does the search
converge within the budget?). A run with ASHA (`scheduler = "asha"`) has configurations it stopped early: they
have no objective, are counted per method (`stopped_early`) and never chosen. Only runs of `asp-dist tune` have
a configurations.parquet; a sweep has none, and then the report has no tuning section.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from asp_dist.analysis.document import Block, Heading, Table, Text
from asp_dist.errors import SpecError
from asp_dist.results.location import as_path
from asp_dist.sweep.ledger import TUNE_CONFIGURATIONS as CONFIGURATIONS  # what asp-dist tune writes
from asp_dist.sweep.ledger import TUNE_PLAN_FILE as PLAN_FILE
from asp_dist.sweep.tune_plan import winning_configuration


def read_configurations(result) -> pd.DataFrame:
    """Every configuration of the input tune runs (columns of configurations.parquet, plus run, domain and
    higher_is_better); empty when no input is a tune run."""
    frames = []
    for sweep_dir in (result.inputs.sweep_dirs if result.inputs is not None else []):
        path = as_path(sweep_dir) / CONFIGURATIONS
        if not path.exists():
            continue
        try:
            table = pd.read_parquet(str(path)) if isinstance(path, Path) else pd.read_parquet(path.open_input())
            plan = json.loads((as_path(sweep_dir) / PLAN_FILE).read_text())
            domain = plan["domain"]
        except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as err:
            raise SpecError(f"{sweep_dir} holds a {CONFIGURATIONS} or {PLAN_FILE} that cannot be read "
                            f"({type(err).__name__}); the tune run's files are damaged") from None
        layout = result.layouts.get(domain)
        higher = layout.higher_is_better if layout is not None else True
        frames.append(table.assign(run=as_path(sweep_dir).name, domain=domain, higher_is_better=higher))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _scored(configs: pd.DataFrame) -> pd.DataFrame:
    """The configurations with no objective where ASHA stopped them (configurations.parquet has none there)."""
    if "stopped_early" not in configs:
        return configs
    return configs.assign(objective=configs["objective"].where(~configs["stopped_early"].eq(True)))


def _knob_columns(configs: pd.DataFrame) -> list[str]:
    return [c for c in configs.columns if c.startswith("knob_")]


def best_table(configs: pd.DataFrame) -> pd.DataFrame:
    """Each (run, method): its best configuration (ties: the lower index), its values and objective, and
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
    """The objective over each method's configurations: quartiles and range (sensitivity to its knobs), and
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
    """One figure per tune run: each method's objective by configuration index (dots) and its best so far (line)."""
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


def tuning_blocks(configs: pd.DataFrame) -> list[Block]:
    """The report's section, or nothing when no input is a tune run."""
    if configs.empty:
        return []
    return [Heading(2, "Tuning: every method on the same budget"),
            Text("Each method's best configuration by its own objective (the median of the metric over its "
                 "calibration cells), beside configuration 0 (its defaults, where the run started from them):"),
            Table(best_table(configs)),
            *([Text("`stopped_early`: the configurations ASHA stopped on their learning curves; they have no "
                    "objective and are never chosen (configurations.parquet has the curve point each was stopped "
                    "at and its objective there).")]
              if "stopped_early" in configs and configs["stopped_early"].eq(True).any() else []),
            Text("The objective over every configuration a method tried: its spread says how much the method's "
                 "knobs matter; `last_improved_at` is the configuration that last raised the best so far (near the "
                 "budget's end: the search had not settled). The figure `tuning_<run>` plots it."),
            Table(spread_table(configs))]
