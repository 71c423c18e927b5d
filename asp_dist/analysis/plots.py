"""The paper's figures from the stats job's result (matplotlib, Agg backend, PNG and SVG).

- metric vs paired count per domain: median line and first–third quartile band per treatment,
  one panel per condition (e.g. per skew or latent size);
- metric vs a numeric knob (VAE latent size, signaling skew …), one panel per paired count;
- the effect of ASP (median paired difference ASP − other, bootstrap 95 % interval) against a
  numeric knob — for the signaling game, against the token-distribution skew;
- the figures only a domain can draw, from its rows' ``figure_data`` (Domain.draw_figures; the VAE's latent
  codes and reconstructions, the levers' communication PCA), with the generic pieces here (scatter_figures,
  pick_rows, save_figure);
- learning curves (a sweep directory's curves/ dataset, asp_dist.results.store.read_curves): a
  few key series (D(fake), discriminator loss and accuracy on fake, the probe metrics) against
  the training step, one panel per paired count, median line and quartile band over trials per
  treatment; one figure per (series, condition), at most MAX_CURVE_FIGURES_PER_DOMAIN per domain.

Every y axis names the metric with its unit and says which direction is better.
(About 520 lines, over the project's 500: each figure is a short function, and they share the style, the
panel layout, the axis labels and the saving; split by kind, every part would import the same helpers back.)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pyarrow as pa  # noqa: E402

from asp_dist.analysis.job import StatsResult  # noqa: E402
from asp_dist.analysis.layout import condition_key, is_asp, treatment_order  # noqa: E402
from asp_dist.analysis.paper import knob_label, metric_label  # noqa: E402
from asp_dist.analysis.rank_tests import bootstrap_median_ci, group_seed  # noqa: E402
from asp_dist.errors import SchemaError  # noqa: E402
from asp_dist.results import store  # noqa: E402
from asp_dist.results.location import as_path  # noqa: E402

METHOD_COLORS = {"pc": "#7f7f7f", "osp": "#1f77b4", "asp": "#d62728"}
MAX_PANELS = 8
MAX_FIGURES_PER_KIND = 12
# Learning-curve series drawn, in this order, when the curves have data for them.
CURVE_SERIES = ("d_fake", "loss_disc", "disc_acc_fake", "probe_mixed", "probe_self_play_new")
MAX_CURVE_FIGURES_PER_DOMAIN = 10
CURVE_LABELS = {
    "d_fake": "D(fake): discriminator's mean output on\nthe new agents' outputs (1 = judged base-like)",
    "loss_disc": "discriminator loss (binary cross-entropy, nats)",
    "disc_acc_fake": "discriminator accuracy on the\nnew agents' outputs (fraction)",
}


@dataclass
class Figure:
    name: str  # file stem under figures/
    title: str
    caption: str
    paths: list[Path]


def y_label(domain: str, metric: str, higher: bool) -> str:
    """The metric with its unit (the domain's PaperFacts) and which direction is better."""
    return f"{metric_label(domain, metric)}\n({'↑ higher' if higher else '↓ lower'} is better)"


def _style(treatment: str, i: int) -> dict[str, Any]:
    method = treatment.split("[")[0]
    styles = ["-", "--", ":", "-."]
    return {"color": METHOD_COLORS.get(method, f"C{i}"), "linestyle": styles[i % len(styles)] if "[" in treatment else "-",
            "marker": "o", "markersize": 4, "label": treatment.upper() if "[" not in treatment else treatment}


def _use_log2(values: np.ndarray) -> bool:
    v = np.asarray(sorted(set(values)), dtype=float)
    positive = v[v > 0]
    return len(positive) >= 3 and positive.max() / positive.min() >= 8


def _maybe_log_y(axes: list[plt.Axes], low: pd.Series, high: pd.Series) -> None:
    """Log y axis for positive metrics spanning more than a decade (VAE MSE: 0.006 … 0.1)."""
    lo, hi = float(np.nanmin(low)), float(np.nanmax(high))
    if lo > 0 and hi / lo >= 20:
        for ax in axes:
            ax.set_yscale("log")


def save_figure(fig: plt.Figure, out_dir: Path, stem: str) -> list[Path]:
    """Write `fig` as PNG and SVG under `out_dir` and close it.

    The layout and the tight bounding box are computed once and kept for both files: ``savefig(bbox_inches=
    "tight")`` would lay the figure out and draw it twice per file (a dry run to measure, then the real
    one), which made figures most of a stats job's time. Both are in inches, the same at either dpi."""
    out_dir.mkdir(parents=True, exist_ok=True)
    renderer = fig.canvas.get_renderer()
    engine = fig.get_layout_engine()
    if engine is not None:
        engine.execute(fig)  # constrained layout, once
        fig.set_layout_engine("none")  # keep these positions for both files
    bbox = fig.get_tightbbox(renderer).padded(plt.rcParams["savefig.pad_inches"])
    paths = []
    for ext in ("png", "svg"):
        path = out_dir / f"{stem}.{ext}"
        fig.savefig(path, dpi=130 if ext == "png" else None, bbox_inches=bbox)
        paths.append(path)
    plt.close(fig)
    return paths


def _panels(n: int) -> tuple[plt.Figure, list[plt.Axes]]:
    cols = n if n <= 4 else 3
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False, sharey=True,
                             layout="constrained")
    flat = list(axes.ravel())
    for ax in flat[n:]:
        ax.set_visible(False)
    return fig, flat[:n]


def safe_name(text: str) -> str:
    """`text` as a file stem."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)[:80]


# ---- metric vs paired -------------------------------------------------------------------------------

def plot_metric_vs_paired(result: StatsResult, domain: str, out_dir: Path) -> Figure | None:
    summary = result.tables["summary"]
    s = summary[summary["domain"] == domain]
    if s.empty:
        return None
    layout = result.layouts[domain]
    # Conditions swept over a single paired count (e.g. the VAE latent-size sweep) belong to the knob figure.
    conditions = [c for c in sorted(s["condition"].unique(), key=condition_key) if s.loc[s["condition"] == c, "paired"].nunique() >= 2]
    if not conditions:
        return None
    conditions = conditions[:MAX_PANELS]
    fig, axes = _panels(len(conditions))
    log2 = _use_log2(s["paired"].to_numpy())
    for ax, cond in zip(axes, conditions):
        sc = s[s["condition"] == cond]
        for i, treat in enumerate(treatment_order(sc["treatment"])):
            g = sc[sc["treatment"] == treat].sort_values("paired")
            style = _style(treat, i)
            ax.plot(g["paired"], g["median"], **style)
            ax.fill_between(g["paired"], g["q1"], g["q3"], color=style["color"], alpha=0.15, linewidth=0)
        if log2:
            ax.set_xscale("symlog", base=2, linthresh=1)
        ax.set_xticks(sorted(sc["paired"].unique()))
        ax.set_xticklabels([str(p) for p in sorted(sc["paired"].unique())])
        ax.set_xlabel(knob_label(domain, "paired"))
        if cond != "all":
            ax.set_title(cond, fontsize=10)
        ax.grid(alpha=0.3)
    _maybe_log_y(axes, s["q1"], s["q3"])
    axes[0].set_ylabel(y_label(domain, result.config.metric, layout.higher_is_better))
    axes[0].legend(fontsize=8)
    n_trials = int(result.rows.loc[result.rows["domain"] == domain, "trial"].nunique())
    fig.suptitle(f"{domain}: median and quartiles over {n_trials} trials", fontsize=11)
    stem = f"{domain}_metric_vs_paired"
    return Figure(stem, f"{domain}: {result.config.metric} against paired count",
                  "Median (line) and first–third quartile band per method; "
                  + ("one panel per condition." if len(conditions) > 1 else ""),
                  save_figure(fig, out_dir, stem))


# ---- metric vs a numeric knob ---------------------------------------------------------------------

def _numeric_knobs(result: StatsResult, domain: str) -> list[str]:
    rows = result.rows[result.rows["domain"] == domain]
    out = []
    for k in result.layouts[domain].shared_knobs:
        values = pd.to_numeric(rows[k], errors="coerce")
        if values.notna().all() and values.nunique() >= 2:
            out.append(k)
    return out


def plot_metric_vs_knob(result: StatsResult, domain: str, knob: str, out_dir: Path) -> list[Figure]:
    summary = result.tables["summary"]
    layout = result.layouts[domain]
    s = summary[summary["domain"] == domain].copy()
    others = [k for k in layout.shared_knobs if k != knob]
    figures = []
    groups = s.groupby(others, sort=True) if others else [((), s)]
    for key, g in list(groups)[:MAX_FIGURES_PER_KIND]:
        key = key if isinstance(key, tuple) else (key,)
        suffix = ", ".join(f"{k}={v}" for k, v in zip(others, key))
        # Panels: paired counts at which the knob takes at least two values.
        counts = [p for p, gp in g.groupby("paired") if gp[knob].nunique() >= 2][-MAX_PANELS:]
        if not counts:
            continue
        fig, axes = _panels(len(counts))
        log2 = _use_log2(g[knob].to_numpy())
        for ax, paired in zip(axes, counts):
            gp = g[g["paired"] == paired]
            for i, treat in enumerate(treatment_order(gp["treatment"])):
                t = gp[gp["treatment"] == treat].sort_values(knob)
                style = _style(treat, i)
                ax.plot(t[knob], t["median"], **style)
                ax.fill_between(t[knob].astype(float), t["q1"], t["q3"], color=style["color"], alpha=0.15, linewidth=0)
            ticks = sorted(gp[knob].unique())
            if log2:
                ax.set_xscale("log", base=2)
            if log2 or len(ticks) <= 8:
                ax.set_xticks(ticks)
                ax.set_xticklabels([f"{v:g}" for v in ticks])
            ax.set_xlabel(knob_label(domain, knob))
            ax.set_title(f"{paired} paired" + (f", {suffix}" if suffix else ""), fontsize=10)
            ax.grid(alpha=0.3)
        _maybe_log_y(axes, g["q1"], g["q3"])
        axes[0].set_ylabel(y_label(domain, result.config.metric, layout.higher_is_better))
        axes[0].legend(fontsize=8)
        fig.suptitle(f"{domain}: {result.config.metric} against {knob} (median and quartiles)", fontsize=11)
        stem = safe_name(f"{domain}_metric_vs_{knob}" + (f"_{suffix}" if suffix else ""))
        figures.append(Figure(stem, f"{domain}: {result.config.metric} against {knob}" + (f" ({suffix})" if suffix else ""),
                              "Median and quartile band per method, one panel per paired count.",
                              save_figure(fig, out_dir, stem)))
    return figures


def plot_asp_effect_vs_knob(result: StatsResult, domain: str, knob: str, out_dir: Path) -> Figure | None:
    """Median paired difference ASP − other per knob value (blocks = trials), with bootstrap 95 % CI."""
    rows = result.rows[result.rows["domain"] == domain]
    layout = result.layouts[domain]
    others_knobs = [k for k in layout.shared_knobs if k != knob]
    if others_knobs and rows[others_knobs].drop_duplicates().shape[0] > 1:
        return None  # the effect is only drawn when the knob is the only condition
    treatments = treatment_order(rows["treatment"])
    asps = [t for t in treatments if is_asp(t)]
    opponents = [t for t in treatments if not is_asp(t)]
    if not asps or not opponents:
        return None
    sign = 1.0 if layout.higher_is_better else -1.0
    fig, axes = _panels(len(opponents))
    paired_counts = sorted(rows["paired"].unique())
    cmap = plt.get_cmap("viridis", max(2, len(paired_counts)))
    # Each (paired, value) block of trials × treatments once, not once per pair of treatments (a tune run has
    # dozens of treatments, each at its own values).
    wides = {paired: [(value, g.pivot_table(index=["root_seed", "trial"], columns="treatment", values="score",
                                            aggfunc="mean"))
                      for value, g in rows[rows["paired"] == paired].groupby(knob, sort=True)]
             for paired in paired_counts}
    for ax, other in zip(axes, opponents):
        for asp in asps:
            for j, paired in enumerate(paired_counts):
                xs, meds, los, his = [], [], [], []
                for value, wide in wides[paired]:
                    if asp not in wide or other not in wide:
                        continue
                    diff = sign * (wide[asp] - wide[other]).dropna().to_numpy()
                    if len(diff) == 0:
                        continue
                    lo, hi = bootstrap_median_ci(diff, result.config.n_boot, result.config.ci,
                                                 group_seed(result.config.seed, "effect", domain, knob, value, asp, other, paired))
                    xs.append(float(value)), meds.append(float(np.median(diff))), los.append(lo), his.append(hi)
                if not xs:
                    continue
                meds_a, los_a, his_a = np.array(meds), np.array(los), np.array(his)
                ax.errorbar(np.array(xs) + 0.02 * (j - len(paired_counts) / 2) * (max(xs) - min(xs) or 1), meds_a,
                            yerr=[meds_a - los_a, his_a - meds_a], marker="o", markersize=4, capsize=2,
                            color=cmap(j), label=f"{paired} paired" + (f" ({asp})" if len(asps) > 1 else ""))
        ax.axhline(0, color="black", linewidth=0.8)
        ax.set_xlabel(knob_label(domain, knob))
        ax.set_title(f"ASP − {other.upper()}", fontsize=10)
        ax.grid(alpha=0.3)
    unit = metric_label(domain, result.config.metric)
    better = "above 0: ASP better" if layout.higher_is_better else "below 0: ASP better"
    axes[0].set_ylabel(f"median paired difference in\n{unit} ({better})")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{domain}: effect of ASP against {knob} (bootstrap 95 % interval over trials)", fontsize=11)
    stem = safe_name(f"{domain}_asp_effect_vs_{knob}")
    return Figure(stem, f"{domain}: effect of ASP against {knob}",
                  "Median over trials of the paired difference ASP − other method at the same (trial, paired), "
                  "with a percentile-bootstrap 95 % interval.", save_figure(fig, out_dir, stem))


# ---- figures a domain draws from its rows' figure_data ------------------------------------------------

def _figure_payloads(rows: pd.DataFrame) -> list[tuple[dict, dict]]:
    """(row, payload) of every row whose figure_data is a JSON object with a "kind"."""
    out = []
    if "figure_data" not in rows:
        return out
    for rec in rows[rows["figure_data"].notna()].to_dict("records"):
        try:
            data = json.loads(rec["figure_data"]) if isinstance(rec["figure_data"], str) else rec["figure_data"]
        except ValueError:
            continue
        if isinstance(data, dict) and isinstance(data.get("kind"), str):
            out.append((rec, data))
    return out


def _pca2(x: np.ndarray) -> np.ndarray:
    x = x - x.mean(axis=0, keepdims=True)
    if x.shape[1] <= 2:
        return x if x.shape[1] == 2 else np.hstack([x, np.zeros((len(x), 2 - x.shape[1]))])
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    return x @ vt[:2].T


def _scatter(ax: plt.Axes, points: np.ndarray, colors: np.ndarray, title: str) -> Any:
    sc = ax.scatter(points[:, 0], points[:, 1], c=colors, cmap="tab10", vmin=-0.5, vmax=9.5, s=6, alpha=0.8, linewidths=0)
    ax.set_title(title, fontsize=9)
    ax.set_xticks([]), ax.set_yticks([])
    return sc


def plot_figure_data(result: StatsResult, out_dir: Path) -> tuple[list[Figure], list[str]]:
    """The figures each domain draws from its rows' figure_data (Domain.draw_figures: VAE latents and
    reconstructions, the levers' communication PCA), domain by domain; the core names no kind."""
    from asp_dist.core.registry import DOMAINS

    by_domain: dict[str, list[tuple[dict, dict]]] = {}
    for rec, data in _figure_payloads(result.rows):
        by_domain.setdefault(str(rec["domain"]), []).append((rec, data))
    figures, notes = [], []
    for domain, payloads in sorted(by_domain.items()):
        card = DOMAINS.get(domain)
        if card is None:
            notes.append(f"figure_data of {domain} not drawn: the domain is not installed here")
            continue
        drawn, more = card.draw_figures(payloads, out_dir)
        figures += drawn
        notes += more
    return figures, notes


def scatter_figures(payloads: list[tuple[dict, dict]], out_dir: Path, *, kind: str, color_key: str,
                    color_label: str, what: str, pca: bool = False) -> tuple[list[Figure], list[str]]:
    """For a domain's figure_data of `kind` (``{"kind", "base", "new", <color_key>}``: points of the base and the
    new agents, one colour index 0-9 per point): per condition, the base and ASP (or the only method) at up to
    4 paired counts of the lowest trial, side by side; `pca`: each panel projected on its first two principal
    components. A payload that does not fit is a note, not an error."""
    figures, notes = [], []
    by_cond: dict[tuple, list[tuple[dict, dict]]] = {}
    for rec, data in payloads:
        if data.get("kind") == kind:
            by_cond.setdefault((rec["domain"], rec["condition"]), []).append((rec, data))
    for (domain, cond), items in sorted(by_cond.items())[:MAX_FIGURES_PER_KIND]:
        try:
            trial, prefer = pick_rows(items, 4)
            first = prefer[0][1]
            panels = [("Base model", np.asarray(first["base"], float), np.asarray(first[color_key]))]
            for rec, data in prefer:
                panels.append((f"{rec['treatment'].upper()} + {rec['paired']} paired",
                               np.asarray(data["new"], float), np.asarray(data[color_key])))
            fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels), 3.2), squeeze=False,
                                     layout="constrained")
            for ax, (title, pts, colors) in zip(axes[0], panels):
                if pts.ndim != 2 or len(pts) != len(colors):
                    raise ValueError(f"{title}: {pts.shape} points but {len(colors)} colours")
                sc = _scatter(ax, _pca2(pts) if pca else pts, colors, title)
            cbar = fig.colorbar(sc, ax=list(axes[0]), ticks=range(10), fraction=0.02)
            cbar.set_label(color_label)
        except (KeyError, ValueError, TypeError) as err:
            plt.close("all")
            notes.append(f"figure_data of {domain} ({kind}, {cond}) not drawn: {err}")
            continue
        fig.suptitle(f"{domain}, trial {trial}" + (f", {cond}" if cond != "all" else "") + f": {what}", fontsize=10)
        stem = safe_name(f"{domain}_{kind}_{cond}")
        figures.append(Figure(stem, f"{domain}: {what}", f"Trial {trial}; each panel projected on its own.",
                              save_figure(fig, out_dir, stem)))
    return figures, notes


def pick_rows(items: list[tuple[dict, dict]], most: int) -> tuple[int, list[tuple[dict, dict]]]:
    """Rows of the lowest trial, ASP preferred, at up to `most` paired counts spread over the range."""
    trial = min(int(r["trial"]) for r, _ in items)
    items = [(r, d) for r, d in items if int(r["trial"]) == trial]
    prefer = sorted([(r, d) for r, d in items if is_asp(r["treatment"])] or items, key=lambda rd: int(rd[0]["paired"]))
    if len(prefer) > most:
        prefer = [prefer[i] for i in np.linspace(0, len(prefer) - 1, most).round().astype(int)]
    return trial, prefer


# ---- learning curves --------------------------------------------------------------------------

def load_curves(result: StatsResult) -> tuple[pd.DataFrame | None, list[str]]:
    """The learning curves of the input sweep directories that have a curves/ folder, or None.

    Merged .parquet inputs and plain directories have no curves; that is not an error."""
    dirs = [as_path(d) for d in (result.inputs.sweep_dirs if result.inputs is not None else [])
            if (as_path(d) / store.CURVES_DIR).is_dir()]
    frames, notes = [], []
    for d in dirs:
        try:
            frames.append(store.read_curves(d))
        except (SchemaError, OSError, ValueError, pa.ArrowException) as err:
            notes.append(f"learning curves of {d} not read: {err}")
    frames = [f for f in frames if not f.empty]
    return (pd.concat(frames, ignore_index=True) if frames else None), notes


def _metric_directions(rows: pd.DataFrame) -> dict[str, bool]:
    """metric name -> higher is better, from the rows' metric_directions JSON."""
    found: dict[str, bool] = {}
    if "metric_directions" not in rows:
        return found
    for text in rows["metric_directions"].dropna().unique():
        try:
            found.update({k: v == "higher" for k, v in json.loads(text).items()})
        except (TypeError, ValueError, AttributeError):
            continue
    return found


def curve_y_label(domain: str, series: str, directions: dict[str, bool]) -> str:
    if series.startswith("probe_"):
        name = series.removeprefix("probe_")
        what = f"probe: {metric_label(domain, 'eval_' + name)}"
        if name in directions:
            return f"{what}\n({'↑ higher' if directions[name] else '↓ lower'} is better)"
        return what
    return CURVE_LABELS.get(series, series)


def _spread(values: list, most: int) -> list:
    """At most `most` of the sorted `values`, spread over the range (first and last kept)."""
    if len(values) <= most:
        return values
    return [values[i] for i in np.linspace(0, len(values) - 1, most).round().astype(int)]


def plot_curves(result: StatsResult, curves: pd.DataFrame, domain: str, out_dir: Path) -> tuple[list[Figure], list[str]]:
    """One figure per (series, condition) of a domain: x = training step, one panel per paired count,
    per treatment the median over trials (line) and the first–third quartile band."""
    rows = result.rows[result.rows["domain"] == domain]
    labels = rows[["cell_id", "treatment", "condition"]].drop_duplicates("cell_id")
    c = curves[curves["domain"] == domain].drop(columns=["treatment", "condition"], errors="ignore")
    c = c.drop_duplicates(["cell_id", "step"]).merge(labels, on="cell_id", how="inner")
    if c.empty:
        return [], []
    directions = _metric_directions(rows)
    # Conditions with the most paired counts first (a paired-count grid before a knob grid's single
    # count), so that the figures kept under the cap are the ones with panels to compare.
    n_paired = c.groupby("condition")["paired"].nunique()
    conditions = sorted(c["condition"].unique(), key=lambda cond: (-n_paired[cond], condition_key(cond)))
    wanted = [(cond, series) for cond in conditions
              for series in CURVE_SERIES if series in c and c.loc[c["condition"] == cond, series].notna().any()]
    notes = []
    if len(wanted) > MAX_CURVE_FIGURES_PER_DOMAIN:
        left = wanted[MAX_CURVE_FIGURES_PER_DOMAIN:]
        notes.append(f"{domain}: {len(left)} learning-curve figure(s) beyond the first {MAX_CURVE_FIGURES_PER_DOMAIN} "
                     f"were not drawn (e.g. {left[0][1]} at {left[0][0]})")
        wanted = wanted[:MAX_CURVE_FIGURES_PER_DOMAIN]
    order = treatment_order(rows["treatment"])  # one style per treatment across panels and figures
    figures = []
    for cond, series in wanted:
        cs = c[(c["condition"] == cond) & c[series].notna()]
        counts = _spread(sorted(cs["paired"].unique()), MAX_PANELS)
        fig, axes = _panels(len(counts))
        sparse = cs.groupby("cell_id").size().median() <= 15  # probes: ~10 points per cell, so mark them
        for ax, paired in zip(axes, counts):
            cp = cs[cs["paired"] == paired]
            for i, treat in enumerate(order):
                t = cp[cp["treatment"] == treat]
                if t.empty:
                    continue
                q = t.groupby("step")[series].quantile([0.25, 0.5, 0.75]).unstack().sort_index()
                style = _style(treat, i)
                if not sparse:
                    style["marker"] = None
                ax.plot(q.index, q[0.5], **style)
                ax.fill_between(q.index, q[0.25], q[0.75], color=style["color"], alpha=0.15, linewidth=0)
            ax.set_xlabel("training step (updates)")
            ax.set_title(f"{paired} paired", fontsize=10)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel(curve_y_label(domain, series, directions))
        handles: dict[str, Any] = {}
        for ax in axes:  # every treatment drawn in any panel, even one absent from the first
            for h, lab in zip(*ax.get_legend_handles_labels()):
                handles.setdefault(lab, h)
        # Below the panels: treatment labels of a calibration grid are long and would cover the data.
        fig.legend(list(handles.values()), list(handles), fontsize=8, loc="upper center",
                   bbox_to_anchor=(0.5, 0.0), ncol=min(2, len(handles)), frameon=False)
        where = f", {cond}" if cond != "all" else ""
        n_trials = int(cs.drop_duplicates("cell_id")["trial"].nunique())
        fig.suptitle(f"{domain}{where}: {series} during training (median and quartiles over {n_trials} trials)",
                     fontsize=11)
        stem = safe_name(f"{domain}_curve_{series}" + (f"_{cond}" if cond != "all" else ""))
        figures.append(Figure(stem, f"{domain}: learning curve of {series}" + (f" ({cond})" if cond != "all" else ""),
                              "Median over trials (line) and first–third quartile band per method against the "
                              "training step, one panel per paired count."
                              + (" Probe values are a cheap evaluation on a tenth of the evaluation episodes, "
                                 "recorded at about ten points per cell." if series.startswith("probe_") else ""),
                              save_figure(fig, out_dir, stem)))
    return figures, notes


def plot_all(result: StatsResult, out_dir: str | Path,
             curves: pd.DataFrame | None = None) -> tuple[list[Figure], list[str]]:
    """Every figure the rows support, written under `out_dir` (…/figures). Returns figures and notes.

    Learning-curve figures come from `curves` when given, else from the input sweep directories'
    curves/ folders (none for merged .parquet inputs)."""
    out = Path(out_dir)
    figures: list[Figure] = []
    for domain in sorted(result.layouts):
        fig = plot_metric_vs_paired(result, domain, out)
        if fig:
            figures.append(fig)
        for knob in _numeric_knobs(result, domain):
            figures.extend(plot_metric_vs_knob(result, domain, knob, out))
            effect = plot_asp_effect_vs_knob(result, domain, knob, out)
            if effect:
                figures.append(effect)
    scatter, notes = plot_figure_data(result, out)
    curve_notes: list[str] = []
    if curves is None:
        curves, curve_notes = load_curves(result)
    curve_figures = []
    if curves is not None and not curves.empty:
        for domain in sorted(result.layouts):
            figs, more = plot_curves(result, curves, domain, out)
            curve_figures.extend(figs)
            curve_notes.extend(more)
    return figures + scatter + curve_figures, notes + curve_notes
