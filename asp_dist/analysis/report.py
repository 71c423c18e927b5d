"""The sweep report: what was run, whether ASP beat OSP and PC (where, and how sure), tables, figures, tests.

The report is written from the stats tables only (no recomputation), so it always agrees with
``stats/*.parquet``. The top section answers the question at a glance; the rest documents.
build_report says it once, as a document.Document; report.md and report.html (html_report.py)
are two renderings of that one document.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from asp_dist.analysis.document import Block, Document, Heading, Plot, Table, Text, render_markdown, write_atomic
from asp_dist.analysis.job import StatsResult
from asp_dist.analysis.layout import is_asp, treatment_order
from asp_dist.analysis.markdown import format_cell
from asp_dist.analysis.paper import paper_claim
from asp_dist.analysis.plots import Figure
from asp_dist.analysis.sequential_report import decide_blocks, read_decisions
from asp_dist.analysis.tuning import read_configurations, tune_grid, tuning_blocks
from asp_dist.results.grouping import treatment_label


def _p(p: float) -> str:
    if p is None or (isinstance(p, float) and np.isnan(p)):
        return "–"
    return f"{p:.2g}" if p >= 1e-3 else f"{p:.1e}"


def pair_verdict(rec: pd.Series, alpha: float) -> str:
    """'**better**', '**worse**' or 'n.s.' for ASP (rec.a) against rec.b, with the evidence."""
    nemenyi = rec.get("p_nemenyi")
    has_nemenyi = nemenyi is not None and not (isinstance(nemenyi, float) and np.isnan(nemenyi))
    evidence = (f"Δ {rec['median_diff']:+.3g}, {rec['wins_a']}–{rec['ties']}–{rec['wins_b']} of {rec['n_blocks']}, "
                + (f"Nemenyi p {_p(nemenyi)}, " if has_nemenyi else "") + f"Wilcoxon–Holm p {_p(rec['p_holm'])}")
    word = "better" if rec["better"] == rec["a"] else "worse" if rec["better"] == rec["b"] else "tied"
    if rec["significant"]:
        caveat = "" if rec.get("views_agree", True) else "; Wilcoxon–Holm does not confirm"
        return f"**{word}** ({evidence}{caveat})"
    if rec.get("significant_wilcoxon_holm"):
        return f"n.s. by Nemenyi, {word} by Wilcoxon–Holm ({evidence})"
    return f"n.s. ({evidence})"


def glance_table(result: StatsResult) -> pd.DataFrame:
    tests, pairwise = result.tables["tests"], result.tables["pairwise"]
    out = []
    if tests.empty:
        return pd.DataFrame()
    for rec in tests.to_dict("records"):
        row = {"domain": rec["domain"], "condition": rec["condition"], "paired range": rec["paired_range"],
               "blocks": rec.get("n_blocks", 0),
               "omnibus": f"{rec['test']} p {_p(rec.get('p_value'))}" if rec["test"] != "none" else rec.get("note", "")}
        pw = pairwise[(pairwise["domain"] == rec["domain"]) & (pairwise["condition"] == rec["condition"])] \
            if not pairwise.empty else pairwise
        for _, p in pw.iterrows():
            if is_asp(p["a"]) and not is_asp(p["b"]):
                row[f"{p['a'].upper()} vs {p['b'].upper()}"] = pair_verdict(p, result.config.alpha)
        out.append(row)
    return pd.DataFrame(out)


def headline_sentences(result: StatsResult) -> list[str]:
    """One plain sentence per (domain, condition): did ASP beat both, one, or neither."""
    lines = []
    pairwise = result.tables["pairwise"]
    if pairwise.empty:
        return ["No condition had two methods with complete blocks to compare."]
    for (domain, cond), g in pairwise.groupby(["domain", "condition"], sort=False):
        asp_pairs = g[g["a"].map(is_asp) & ~g["b"].map(is_asp)]
        if asp_pairs.empty:
            lines.append(f"- **{domain}** ({cond}): no ASP rows to compare.")
            continue
        beaten = [p["b"].upper() for _, p in asp_pairs.iterrows() if p["significant"] and p["better"] == p["a"]]
        lost = [p["b"].upper() for _, p in asp_pairs.iterrows() if p["significant"] and p["better"] == p["b"]]
        others = [p["b"].upper() for _, p in asp_pairs.iterrows()]
        rng = asp_pairs["paired_range"].iloc[0]
        if beaten and len(beaten) == len(others):
            verdict = f"ASP beat {' and '.join(beaten)}"
        elif beaten:
            verdict = f"ASP beat {' and '.join(beaten)}, not significantly different from the rest"
        else:
            verdict = "no significant advantage for ASP"
        if lost:
            verdict += f"; ASP was significantly worse than {' and '.join(lost)}"
        def evidence(p: pd.Series) -> str:
            nem = p.get("p_nemenyi")
            main = f"Nemenyi p {_p(nem)}" if nem is not None and not np.isnan(nem) else f"Wilcoxon p {_p(p['p_holm'])}"
            second = f", Wilcoxon–Holm p {_p(p['p_holm'])}" if main.startswith("Nemenyi") else ""
            return (f"vs {p['b'].upper()}: {main}{second}, ASP ahead in {p['wins_a']}, behind in {p['wins_b']} "
                    f"of {p['n_blocks']} blocks")

        ps = "; ".join(evidence(p) for _, p in asp_pairs.iterrows())
        disagree = [p["b"].upper() for _, p in asp_pairs.iterrows() if not p.get("views_agree", True)]
        if disagree:
            verdict += f" (the two post-hoc views disagree on {' and '.join(disagree)})"
        lines.append(f"- **{domain}** ({cond}, paired {rng}): {verdict} ({ps}; α = {result.config.alpha}).")
    return lines


def where_table(result: StatsResult) -> pd.DataFrame:
    """Paired counts x (condition, opponent): ✓ ASP significantly better, ✗ worse, + / − direction only."""
    bp = result.tables["by_paired"]
    if bp.empty:
        return pd.DataFrame()
    out = []
    for (domain, cond, paired), g in bp.groupby(["domain", "condition", "paired"], sort=False):
        row = {"domain": domain, "condition": cond, "paired": int(paired)}
        for _, p in g.iterrows():
            mark = "=" if p["better"] == "tie" else ("+" if p["better"] == p["a"] else "−")
            if p["significant"]:
                mark = "✓" if p["better"] == p["a"] else "✗"
            row[f"{p['a']} vs {p['b']}"] = f"{mark} {p['median_diff']:+.3g}"
        out.append(row)
    return pd.DataFrame(out)


def grid_description(result: StatsResult, configs: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per domain: its rows, methods, paired counts, trials and varied knobs. A tune run's cells are named
    by their configurations (method and index; `configs`: read_configurations, read here when not given), their
    searched values left to the tuning section: listed, a few hundred configurations fill one cell."""
    configs = read_configurations(result) if configs is None else configs
    out = []
    for domain, layout in sorted(result.layouts.items()):
        rows = result.rows[result.rows["domain"] == domain]
        tuned_ids, searched, tuned = tune_grid(configs, domain)
        tuned_rows = rows["cell_id"].isin(tuned_ids) if tuned_ids and "cell_id" in rows else \
            pd.Series(False, index=rows.index)
        outside = rows[~tuned_rows]  # a searched knob's values are listed only from rows outside tune runs
        knobs = {k: sorted((outside if k in searched else rows)[k].dropna().unique().tolist())
                 for k in layout.shared_knobs}
        for m, ks in layout.method_knobs.items():
            for k in ks:
                shown = outside if k in searched else rows
                knobs[f"{k} ({m})"] = sorted(shown.loc[shown["method"] == m, k].dropna().unique().tolist())
        treatments = rows["treatment"].copy()
        for i, rec in zip(rows.index[tuned_rows], rows[tuned_rows].to_dict("records")):  # their searched knobs left out
            treatments[i] = treatment_label(rec["method"], [k for k in layout.method_knobs.get(rec["method"], [])
                                                            if k not in searched], rec)
        described = [f"{k} = {', '.join(format_cell(v) for v in vs)}" for k, vs in knobs.items() if vs or not tuned]
        out.append({"domain": domain, "rows": len(rows),
                    "methods": ", ".join(treatment_order(treatments)),
                    "paired": ", ".join(str(p) for p in sorted(rows["paired"].unique())),
                    "trials": f"{rows['trial'].nunique()} ({rows['trial'].min()}–{rows['trial'].max()})",
                    "varied knobs": "; ".join(described + ([tuned] if tuned else [])) or "none",
                    "direction": "higher is better" if layout.higher_is_better else "lower is better",
                    "sweeps": ", ".join(sorted(rows["sweep_id"].dropna().astype(str).unique())) if "sweep_id" in rows else "–"})
    return pd.DataFrame(out)


def _summary_compact(summary: pd.DataFrame) -> pd.DataFrame:
    s = summary.copy()
    s["median [Q1, Q3]"] = [f"{m:.4g} [{a:.4g}, {b:.4g}]" for m, a, b in zip(s["median"], s["q1"], s["q3"])]
    s["95% CI of median"] = [f"[{a:.4g}, {b:.4g}]" for a, b in zip(s["ci_low"], s["ci_high"])]
    s["mean ± sd"] = [f"{m:.4g} ± {format_cell(sd, 3)}" for m, sd in zip(s["mean"], s["std"])]
    return s[["condition", "treatment", "paired", "n", "median [Q1, Q3]", "95% CI of median", "mean ± sd"]]


def _interval(point: float, low: float, high: float) -> str:
    return f"{point:.2f} [{low:.2f}, {high:.2f}]"


def all_won_lower_bound(n: int, ci: float) -> float:
    """Lower end of the exact (Clopper–Pearson) interval of a proportion after n successes in n trials."""
    return ((1 - ci) / 2) ** (1 / n) if n > 0 else 0.0


def agreement_blocks(agree: pd.DataFrame, ci: float) -> list[Block]:
    """Where the rliable view and the rank tests agree, and where and why they do not."""
    if agree.empty:
        return [Text("_No pair had both a probability of improvement and a rank test._")]
    same = agree["agree_paired"].astype(bool)
    blocks: list[Block] = [Text(
        f"The interval of the paired P(A > B) and the rank tests' verdict agree on **{int(same.sum())} of "
        f"{len(agree)}** pairs (the unpaired P(A > B): {int(agree['agree_unpaired'].astype(bool).sum())} of "
        f"{len(agree)}). A call from P(A > B) is a winner when its {int(ci * 100)} % interval lies entirely "
        "on one side of ½.")]
    differ = []
    for rec in agree[~same].to_dict("records"):
        pair = f"{rec['a'].upper()} vs {rec['b'].upper()}"
        where = f"{rec['domain']}" + (f" ({rec['condition']})" if rec["condition"] != "all" else "")
        if rec["rank_call"] == "n.s.":
            why = (f"P(A > B) calls *{rec['rliable_paired']}* but {rec['rank_test']} is not significant"
                   + (f" (Wilcoxon–Holm: {rec['wilcoxon_holm_call']})" if rec["rank_test"] != "Wilcoxon" else ""))
        elif rec["rliable_paired"] == "uncertain":
            why = f"{rec['rank_test']} calls *{rec['rank_call']}* but the interval of P(A > B) contains ½"
        else:
            why = f"the two views call different winners ({rec['rliable_paired']} against {rec['rank_call']})"
        differ.append(f"- {where}, {pair}: {why}; paired P = "
                      f"{_interval(rec['poi_paired'], rec['poi_paired_ci_low'], rec['poi_paired_ci_high'])} over "
                      f"{rec['n_blocks']} blocks.")
    if differ:
        blocks.append(Text("\n".join(differ)))
    degenerate = agree[(agree["poi_paired_ci_low"] == agree["poi_paired_ci_high"])
                       & agree["poi_paired"].isin([0.0, 1.0])]
    if not degenerate.empty:
        n = int(degenerate["n_blocks"].min())
        blocks.append(Text(
            f"In {len(degenerate)} pair(s) one treatment won every block, so every resample gives the "
            f"same P and the percentile interval has width 0. The bootstrap cannot show uncertainty beyond "
            f"what was observed: with {n} of {n} blocks won, an exact binomial {int(ci * 100)} % interval "
            f"of the block-win probability would reach down to {all_won_lower_bound(n, ci):.2f}."))
    return blocks


def rliable_section(result: StatsResult) -> list[Block]:
    """The rliable view: aggregate IQM, P(A > B) beside the rank tests' verdicts, where the views differ."""
    t, cfg = result.tables, result.config
    blocks: list[Block] = [
        Heading(2, "The rliable view: IQM, probability of improvement, performance profiles"),
        Text("Beside the rank tests, the statistics of Agarwal et al. (NeurIPS 2021, rliable): interquartile means "
             "with stratified-bootstrap intervals and the probability that one method beats another, on a "
             "normalised score (0 = PC's median with the least paired data of the condition, 1 = the base pair's "
             "own self-play score; `stats/normalisation.md`). Definitions under *The tests*.")]
    agg = t.get("aggregate", pd.DataFrame())
    if not agg.empty:
        wide = agg.assign(value=[_interval(p, lo, hi) for p, lo, hi in zip(agg["iqm_norm"], agg["ci_low"],
                                                                             agg["ci_high"])])
        wide = wide.pivot(index="scope", columns="treatment", values="value")
        wide = wide.reindex(index=list(dict.fromkeys(agg["scope"])), columns=treatment_order(agg["treatment"]))
        blocks += [Text("**IQM of the normalised score** over each domain's paired range:"), Table(wide.reset_index())]
    agree = t.get("rliable_agreement", pd.DataFrame())
    if not agree.empty:
        shown = pd.DataFrame({
            "domain": agree["domain"], "condition": agree["condition"], "paired range": agree["paired_range"],
            "pair": [f"P({a.upper()} > {b.upper()})" for a, b in zip(agree["a"], agree["b"])],
            "paired (blocks)": [_interval(p, lo, hi) for p, lo, hi in
                                zip(agree["poi_paired"], agree["poi_paired_ci_low"], agree["poi_paired_ci_high"])],
            "unpaired (runs)": [_interval(p, lo, hi) for p, lo, hi in
                                zip(agree["poi"], agree["poi_ci_low"], agree["poi_ci_high"])],
            "P says": agree["rliable_paired"], "rank test": agree["rank_test"], "rank test says": agree["rank_call"],
            "Wilcoxon–Holm says": agree["wilcoxon_holm_call"], "agree": agree["agree_paired"]})
        blocks += [Text("**P(A > B) and the rank tests**, per condition over the paired range:"), Table(shown)]
    return blocks + agreement_blocks(agree, cfg.ci)


def default_vs_tuned_blocks(result: StatsResult) -> list[Block]:
    """Each method against its @default arm (stats/default_vs_tuned); nothing when no sweep ran one."""
    dvt = result.tables.get("default_vs_tuned", pd.DataFrame())
    if dvt.empty:
        return []
    return [Heading(3, "Default vs tuned"),
            Text("Each method at its tuned setting against its `@default` arm (the knobs' defaults), over the "
                 "paired range's complete blocks; these arms are left out of the tests above. median_diff: tuned − "
                 "default in score units (> 0: tuned better, whichever way the metric points); p: two-sided "
                 "Wilcoxon signed-rank, uncorrected."),
            Table(dvt, ["domain", "condition", "tuned", "default", "paired_range", "n_blocks", "tuned_better",
                        "tuned_worse", "ties", "median_tuned", "median_default", "median_diff", "p_wilcoxon",
                        "better"])]


def min_wilcoxon_p(n: int) -> float:
    """Smallest two-sided p an exact Wilcoxon signed-rank test can give with n non-zero differences."""
    return 2.0 / 2 ** n if n > 0 else 1.0


# What a row records of the code and packages that made it (asp_dist.training.row, the sweep's columns).
PROVENANCE_COLUMNS = ("code_revision", "asp_dist_version", "torch_version", "numpy_version", "python_version",
                      "ray_version", "cpu_model")


def provenance_blocks(rows: pd.DataFrame) -> list[Block]:
    """The report's Provenance section: the distinct code revisions and versions among the rows (per sweep),
    with a warning where a sweep mixes them or has rows from a dirty tree."""
    cols = [c for c in PROVENANCE_COLUMNS if c in rows]
    if not cols:
        return []
    by = "sweep_id" if "sweep_id" in rows and rows["sweep_id"].notna().any() else None
    records, warnings = [], []
    for sweep, group in (rows.groupby(rows[by].fillna("(none)")) if by else [("all rows", rows)]):
        for col in cols:
            counts = group[col].fillna("unknown").astype(str).value_counts()
            records.append({"sweep": sweep, "column": col, "rows": int(counts.sum()),
                            "values": ", ".join(f"{v} ({n})" for v, n in sorted(counts.items()))})
            if col == "cpu_model":  # rows older than the column say "unknown": not a kind of their own
                kinds = len(counts.drop("unknown", errors="ignore"))
                if kinds > 1:
                    warnings.append(f"sweep {sweep} ran on {kinds} kinds of CPU: a row reproduces bit for bit only "
                                    f"on the kind that made it (`asp-dist replay` elsewhere differs in the last bits, "
                                    f"and chaotic training such as a particle base can then take another path)")
            elif len(counts) > 1:
                warnings.append(f"sweep {sweep} mixes {len(counts)} values of {col}: its rows were not all made "
                                f"with the same code and packages")
        dirty = group["code_revision"].astype(str).str.endswith("+dirty").sum() if "code_revision" in group else 0
        if dirty:
            warnings.append(f"sweep {sweep}: {dirty} row(s) from a dirty tree (uncommitted changes): the revision "
                            f"alone does not say what ran; env/<n>/git.diff in the sweep directory does")
    blocks: list[Block] = [Heading(2, "Provenance"),
                           Text("Code revision, package versions and CPU recorded in the rows (value (rows)); each run "
                                "of a sweep also records its command, space file, installed distributions, git "
                                "state, CPU, threads and Ray nodes under `env/<n>/` in the sweep directory."),
                           Table(pd.DataFrame(records))]
    if warnings:
        blocks.append(Text("\n".join(f"- **warning**: {w}" for w in warnings)))
    else:
        blocks.append(Text("One code revision, one version of each package and at most one known kind of CPU in "
                           "every sweep, none from a dirty tree."))
    return blocks


def figure_count_text(n: int) -> str:
    """How many figures the report holds, in words a reader (and the browser check) can count against."""
    if n == 0:
        return "_No figures._"
    return f"{n} figure{'s' if n != 1 else ''}, each also as PNG and SVG in `figures/`."


def _name(result: StatsResult, out_dir: Path) -> str:
    rows = result.rows
    if "sweep_id" in rows and rows["sweep_id"].notna().any():
        return ", ".join(sorted(rows["sweep_id"].dropna().astype(str).unique()))
    return out_dir.name


NARROWED = "; of a tune run, the rows the sentence below names"  # its files are every configuration's


def build_report(result: StatsResult, out_dir: str | Path, figures: Sequence[Figure] = (),
                 figure_notes: Sequence[str] = (), sources: Sequence[str] = (), command: str = "",
                 latex_tables: Sequence[str] = ()) -> Document:
    """What the report says, once for every format (report.md, report.html): at a glance, where, data
    efficiency, the rliable view, what was run, the figures, the tables and the tests."""
    out_dir = Path(out_dir)
    cfg, t = result.config, result.tables
    doc = Document(f"Sweep report: {_name(result, out_dir)}", out_dir)
    doc.add(Heading(1, doc.title),
            Text(f"Generated {datetime.now(timezone.utc).isoformat(timespec='seconds')} from {len(result.rows)} rows"
                 + (f" ({len(result.inputs.files)} files{NARROWED if result.tune_notes else ''})" if result.inputs else "")
                 + f". Metric: `{cfg.metric}`; α = {cfg.alpha}; bootstrap {cfg.n_boot} resamples, seed {cfg.seed}."
                 + (f" Command: `{command}`." if command else "")),
            *(Text(note) for note in result.tune_notes))  # a tune run's statistics speak of a few of its rows

    doc.add(Heading(2, "At a glance: did ASP beat OSP and PC?"),
            Text("\n".join(headline_sentences(result))), Table(glance_table(result)),
            Text("*better / worse*: with three or more methods, the Friedman test over blocks (trial, paired) and the "
                 "Nemenyi post-hoc are both below α (the paper's procedure); the Wilcoxon signed-rank test with Holm's "
                 "correction is shown as a second view. With two methods, the Wilcoxon test decides. Δ = median paired "
                 "difference ASP − other in metric units; a–t–b = blocks where ASP is better – tied – worse."))
    doc.add(*decide_blocks(read_decisions(result)))  # only where `asp-dist decide` grew an input
    claims = [f"- {d}: {claim}" + ("" if claim.endswith((".", "?", "!")) else ".")
              for d in sorted(result.layouts) if (claim := paper_claim(d))]
    if claims:
        doc.add(Text("For comparison, the paper's findings:"), Text("\n".join(claims)))
    trend = t.get("knob_trend", pd.DataFrame())
    if not trend.empty:
        doc.add(Text("**Does ASP's advantage grow with the knob?** Spearman's ρ between the knob and the per-block "
                     "difference ASP − other (all paired counts):"),
                Table(trend, ["domain", "knob", "fixed", "a", "b", "n_blocks", "spearman_rho", "p_value",
                              "knob_min", "median_diff_at_min", "knob_max", "median_diff_at_max"]))

    doc.add(Heading(3, "Where: ASP against each method at every paired count"),
            Text("✓ / ✗: ASP significantly better / worse (Wilcoxon, Holm over all counts and opponents of the "
                 "condition); + / − / =: ASP better / worse / tied, not significant. The number is the median paired "
                 "difference ASP − other in metric units (negative is ASP better when lower is better)."),
            Table(where_table(result)))
    bp = t["by_paired"]
    if not bp.empty:
        typical = int(np.median(bp["n_blocks"]))
        if min_wilcoxon_p(typical) * len(bp) / max(1, bp.groupby(["domain", "condition"]).ngroups) >= cfg.alpha:
            doc.add(Text(f"With typically {typical} blocks per count, the smallest possible two-sided Wilcoxon p is "
                         f"{_p(min_wilcoxon_p(typical))} before Holm's correction: per-count tests cannot reach "
                         "significance at this size; read their direction, and the pooled test above."))

    doc.add(Heading(3, "Paired-data efficiency: does ASP with n match or beat the others with 2n?"))
    claim = t["claim_2n"]
    if claim.empty:
        doc.add(Text("_Not testable: no paired counts n and 2n both present for ASP and another method._"))
    else:
        lines = []
        for (domain, cond, other), g in claim.groupby(["domain", "condition", "other"], sort=False):
            held = [str(n) for n, h in zip(g["n"], g["holds"]) if h]
            sure = [str(n) for n, v in zip(g["n"], g["verdict"]) if v.startswith("beats")]
            lines.append(f"- {domain} ({cond}) vs {other.upper()}: holds (medians) at n = {', '.join(held) or 'none'}"
                         f" of {', '.join(str(n) for n in g['n'])}; with the 95 % interval of ASP's gain above 0 at "
                         f"n = {', '.join(sure) or 'none'}.")
        doc.add(Text("\n".join(lines)),
                Table(claim, ["domain", "condition", "asp", "other", "n", "two_n", "median_asp_n", "median_other_2n",
                              "n_trials", "median_gain", "gain_ci_low", "gain_ci_high", "verdict"]),
                Text("*gain*: ASP at n against the other method at 2n, per trial, in metric units with positive = "
                     "ASP better whichever way the metric points; *beats*: the gain's whole interval is above 0."))
    doc.add(Text("Smallest paired count whose median reaches the threshold:"),
            Table(t["efficiency"], ["domain", "condition", "treatment", "threshold", "threshold_rule",
                                    "min_paired_reaching", "median_there"]))

    doc.add(*default_vs_tuned_blocks(result))
    doc.add(*rliable_section(result))
    configs = read_configurations(result)
    doc.add(*tuning_blocks(configs))  # only where an input is a tune run

    doc.add(Heading(2, "What was run"), Table(grid_description(result, configs)))
    missing = t["missing"]
    notes = list(result.notes) + list(figure_notes)
    if notes:
        doc.add(Text("\n".join(f"- {n}" for n in notes)))
    if missing.empty and result.grid_known:
        doc.add(Text("No missing cells: every planned cell finished and every block has every method."))
    elif missing.empty:
        doc.add(Text("Every block has every method. Without a manifest.json for every input the planned grid "
                     "is unknown, so cells that never started cannot be listed."))
    else:
        doc.add(Text(f"**Missing: {len(missing)} entries** (see `stats/missing.md` for all):"), Table(missing.head(40)))
        if len(missing) > 40:
            doc.add(Text(f"… and {len(missing) - 40} more."))
    if sources:
        doc.add(Text("Inputs: " + ", ".join(f"`{s}`" for s in sources)))
    doc.add(*provenance_blocks(result.rows))

    doc.add(Heading(2, "Figures"), Text(figure_count_text(len(figures))), *(Plot(f) for f in figures))

    doc.add(Heading(2, "Tables"))
    for domain in sorted(result.layouts):
        s = t["summary"][t["summary"]["domain"] == domain]
        doc.add(Heading(3, f"{domain}: per-group statistics of `{cfg.metric}` "
                           f"({'higher' if result.layouts[domain].higher_is_better else 'lower'} is better)"),
                Table(_summary_compact(s)))
    doc.add(Heading(3, "Rank tests over the paired range"),
            Table(t["tests"], ["domain", "condition", "paired_range", "treatments", "n_blocks", "n_blocks_incomplete",
                               "test", "statistic", "p_value", "kendall_w", "mean_ranks", "note"]),
            Heading(3, "Pairwise post-hoc (Nemenyi; Wilcoxon signed-rank with Holm)"),
            Table(t["pairwise"], ["domain", "condition", "a", "b", "n_blocks", "median_a", "median_b", "median_diff",
                                  "wins_a", "ties", "wins_b", "p_nemenyi", "p_wilcoxon", "p_holm", "better",
                                  "significant", "views_agree"]),
            Text("Every table is also in `stats/<name>.parquet` and `stats/<name>.md` "
                 "(summary, tests, pairwise, by_paired, efficiency, claim_2n, knob_trend, default_vs_tuned, "
                 "missing; the rliable view's normalisation, iqm, aggregate, improvement, improvement_by_paired, "
                 "profiles, rliable_agreement)"
                 + (f"; {', '.join(latex_tables)} also as booktabs LaTeX, `stats/<name>.tex`, ready to `\\input`"
                    if latex_tables else "") + "."))

    doc.add(Heading(2, "The tests"), Text(METHODS_TEXT.format(
        alpha=cfg.alpha, n_boot=cfg.n_boot, ci=int(cfg.ci * 100), seed=cfg.seed,
        ranges=json.dumps({k: list(v) if v else "all" for k, v in cfg.paired_ranges.items()}))))
    return doc


def write_report(result: StatsResult, out_dir: str | Path, figures: Sequence[Figure] = (),
                 figure_notes: Sequence[str] = (), sources: Sequence[str] = (), command: str = "") -> Path:
    """report.md of the stats job (build_report + render_markdown)."""
    doc = build_report(result, out_dir, figures, figure_notes, sources, command)
    return write_atomic(doc.out_dir / "report.md", render_markdown(doc))


METHODS_TEXT = """\
- **Blocks.** Within one trial and paired count, PC, OSP and ASP share the base model, the
  paired and unpaired sets and the initial weights, so every comparison is paired over blocks
  (root_seed, trial, paired); blocks missing a method are left out (counted as incomplete).
- **Per-group statistics.** n, median, first and third quartile (linear interpolation), mean,
  sample standard deviation, and a {ci} % percentile-bootstrap interval of the median
  ({n_boot} resamples, seeded from seed {seed} and the group's key, so reruns give the same interval).
- **Omnibus test.** Friedman's χ² over blocks in the domain's paired range ({ranges};
  others: every count), with three or more methods; Kendall's W = χ² / (n (k − 1)) as effect
  size. With exactly two methods, the Wilcoxon signed-rank test over blocks instead.
- **Post-hoc.** Nemenyi's test after Friedman (scikit-posthocs `posthoc_nemenyi_friedman`): a
  pair is called significant when the Friedman p and the pair's Nemenyi p are below α = {alpha}.
  As a second view, two-sided Wilcoxon signed-rank tests of every pair (zero differences
  dropped) with Holm's correction over the pairs; `views_agree` says whether both views reach
  the same call. Nemenyi compares mean ranks over all methods at once and is the more
  conservative of the two when one method ties often with another.
- **Per paired count.** Wilcoxon signed-rank of ASP against each other method at each count,
  Holm-corrected over all counts and opponents of the condition.
- **Data efficiency.** The smallest paired count whose group median reaches the threshold; and
  the paper's claim, checked directly: median of ASP at n against the other method at 2n, with
  a bootstrap interval of the median per-trial gain of ASP (positive = ASP better, for either
  metric direction).
- **Default vs tuned.** A method's `@default` arm (its knobs' defaults, beside the tuned method) is
  left out of the tests above and compared with its method alone: the Wilcoxon signed-rank test over
  the complete blocks of the paired range, uncorrected.
- **Trend with a knob.** Spearman's ρ between a numeric knob (≥ 3 values) and the per-block
  difference ASP − other.
- Metric directions come from the rows (`<metric>_higher_is_better`, `metric_directions`).
- **The rliable view** (Agarwal et al., NeurIPS 2021; asp_dist/analysis/rliable_view.py). A *task* is
  a (domain, condition, paired count). *Normalised score*: (score − zero) / (one − zero) per
  condition, zero = PC's median at 0 paired (else at the smallest count), one = the median of the
  base pair's own self-play score (`eval_self_play_base`), both direction-corrected
  (`stats/normalisation.md`). *IQM*: the mean of the middle half of the runs (⌊n/4⌋ dropped at each
  end). *Stratified bootstrap*: trials resampled within every task independently, {n_boot}
  resamples, {ci} % percentile interval. *P(A > B)*, unpaired: P(X > Y) + ½ P(X = Y) over the runs of
  a task, averaged over tasks (rliable's probability of improvement); paired: the same over blocks
  (1 win, ½ tie, 0 loss), blocks resampled within tasks. *Performance profile*: the fraction of runs
  with normalised score > τ. Pooled statistics use the domain's paired range, like the rank tests.
"""
