"""stats/*.tex: the tables a paper shows, as booktabs ``tabular`` environments ready to ``\\input``.

One file per table: summary (median [Q1, Q3] per method), pairwise (the rank tests' pairs), iqm
(the sample-efficiency table: IQM of the normalised score per method and paired count), aggregate
(that IQM pooled over the paired range) and improvement (P(A > B), paired and unpaired).
Numbers are rounded as in the Markdown (metric units: markdown.format_value's 4 significant digits;
normalised scores and probabilities: 2 decimals, as the report's rliable section). Bold marks the
best value of a row: the best median (in the metric's direction), the largest IQM; in improvement,
where the best is not defined, bold marks a P whose interval lies entirely on one side of ½.
Every label is escaped, and the few non-ASCII signs the labels use are written as LaTeX, so the
files compile with pdflatex and only ``\\usepackage{booktabs}`` (tests/test_stats.py).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from asp_dist.analysis.document import write_atomic
from asp_dist.analysis.job import StatsResult
from asp_dist.analysis.layout import treatment_order
from asp_dist.analysis.markdown import format_value

LATEX_TABLES = ("summary", "pairwise", "iqm", "aggregate", "improvement")

_SPECIALS = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
             "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
             "<": "$<$", ">": "$>$", "|": r"\textbar{}"}
_UNICODE = {"−": "$-$", "–": "--", "—": "---", "Δ": r"$\Delta$", "±": r"$\pm$", "½": r"$\frac{1}{2}$",
            "≥": r"$\geq$", "≤": r"$\leq$", "×": r"$\times$", "α": r"$\alpha$", "ρ": r"$\rho$",
            "λ": r"$\lambda$", "τ": r"$\tau$", "✓": r"$\checkmark$", "·": r"$\cdot$", "…": r"\ldots{}",
            "’": "'", "“": "``", "”": "''"}
_NUMBER = re.compile(r"^(-?)(\d+(?:\.\d+)?)(?:e([+-]?\d+))?$")


def escape(text: str) -> str:
    """A label as LaTeX text: TeX's specials escaped, the report's non-ASCII signs spelled out."""
    return "".join(_SPECIALS.get(c) or _UNICODE.get(c) or c for c in str(text))


def number(text: str) -> str:
    """A rounded number as LaTeX: a real minus sign and 1.2e-05 as 1.2 × 10^−5; anything else escaped."""
    m = _NUMBER.match(text)
    if not m:
        return escape(text)
    sign, mantissa, exponent = m.groups()
    if exponent is None:
        return ("$-$" if sign and mantissa.strip("0.") else "") + mantissa  # no sign on a zero: "-0" is 0
    return rf"${sign}{mantissa}\times10^{{{int(exponent)}}}$"


def label(treatment: str) -> str:
    """PC, OSP, ASP, and a treatment's knob as it is: ASP[lambda_unpaired=0.5] (escaped)."""
    method, bracket, knob = str(treatment).partition("[")
    return escape(method.upper() + bracket + knob)


def value(v) -> str:
    return number(format_value(v))


def interval(point: float, low: float, high: float, digits: int | None = None) -> str:
    """'x [lo, hi]': 4 significant digits (metric units) or `digits` decimals (scores, probabilities)."""
    if digits is None:
        return f"{value(point)} [{value(low)}, {value(high)}]"
    return " ".join([number(f"{point:.{digits}f}"), f"[{number(f'{low:.{digits}f}')}, {number(f'{high:.{digits}f}')}]"])


def bold_first(cell: str) -> str:
    """Bold the cell's point estimate (its first word), not its interval."""
    head, _, rest = cell.partition(" ")
    return rf"\textbf{{{head}}}" + (f" {rest}" if rest else "")


def tabular(header: Sequence[str], rows: Sequence[Sequence[str]], align: str, comment: str,
            breaks: Sequence[int] = ()) -> str:
    """A booktabs tabular: header and cells already LaTeX; a \\midrule before each row index in `breaks`."""
    assert len(align) == len(header) and all(len(r) == len(header) for r in rows)
    lines = [f"% {line}" for line in comment.splitlines()]
    lines += [rf"\begin{{tabular}}{{{align}}}", r"\toprule", " & ".join(header) + r" \\", r"\midrule"]
    for i, row in enumerate(rows):
        if i in breaks:
            lines.append(r"\midrule")
        lines.append(" & ".join(row) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(lines) + "\n"


def _group_breaks(keys: Sequence) -> list[int]:
    """Row indices where the leading key (domain, or domain and condition) changes."""
    return [i for i in range(1, len(keys)) if keys[i] != keys[i - 1]]


def _keys(df: pd.DataFrame) -> list[str]:
    """domain, and condition only when some condition is not the whole domain."""
    return ["domain"] + (["condition"] if "condition" in df and (df["condition"] != "all").any() else [])


def _wide(df: pd.DataFrame, index: list[str], cell: Callable[[pd.Series], str],
          score: Callable[[pd.Series], float], comment: str) -> str:
    """Rows `index`, one column per treatment, the highest score bold per row; with `paired` last in the
    index, a rule between the groups of the keys before it (domain, condition)."""
    methods = treatment_order(df["treatment"])
    by_paired = index[-1] == "paired"
    rows, groups = [], []
    for key, g in df.groupby(index, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        by = {r["treatment"]: r for _, r in g.iterrows()}
        scores = {m: score(r) for m, r in by.items() if not np.isnan(score(r))}
        texts = {m: cell(r) for m, r in by.items()}
        best = texts[max(scores, key=scores.get)].split(" ")[0] if scores else None
        # a tie after rounding is a tie on the page: every cell that shows the best value is bold
        cells = [("--" if m not in by else bold_first(texts[m]) if m in scores and texts[m].split(" ")[0] == best
                  else texts[m]) for m in methods]
        rows.append([escape(k) for k in key] + cells)
        groups.append(key[:-1] if by_paired else ())
    header = [escape(h) for h in index] + [label(m) for m in methods]
    align = "l" * (len(index) - by_paired) + "r" * (by_paired + len(methods))
    return tabular(header, rows, align, comment, _group_breaks(groups))


def summary_tex(result: StatsResult) -> str:
    s = result.tables["summary"]
    if s.empty:
        return ""
    index = _keys(s) + ["paired"]
    sign = {d: 1.0 if layout.higher_is_better else -1.0 for d, layout in result.layouts.items()}
    return _wide(s, index, cell=lambda r: f"{value(r['median'])} [{value(r['q1'])}, {value(r['q3'])}]",
                 score=lambda r: sign[r["domain"]] * float(r["median"]),
                 comment=f"asp-dist stats: median [Q1, Q3] of {result.config.metric} over trials per method "
                         "and paired count.\nBold: the best median of the row (in the metric's direction).")


def iqm_tex(result: StatsResult) -> str:
    q = result.tables.get("iqm", pd.DataFrame())
    if q.empty:
        return ""
    index = _keys(q) + ["paired"]
    return _wide(q, index, cell=lambda r: interval(r["iqm_norm"], r["norm_ci_low"], r["norm_ci_high"], 2),
                 score=lambda r: float(r["iqm_norm"]),
                 comment="asp-dist stats: IQM of the normalised score (0 = PC with the least paired data, 1 = the "
                         "base pair's self-play;\nstats/normalisation.md) with its 95 % stratified-bootstrap "
                         "interval, per method and paired count.\nBold: the largest IQM of the row.")


def aggregate_tex(result: StatsResult) -> str:
    agg = result.tables.get("aggregate", pd.DataFrame())
    if agg.empty:
        return ""
    return _wide(agg, ["scope"], cell=lambda r: interval(r["iqm_norm"], r["ci_low"], r["ci_high"], 2),
                 score=lambda r: float(r["iqm_norm"]),
                 comment="asp-dist stats: IQM of the normalised score pooled over each domain's paired range, "
                         "95 % stratified-bootstrap interval.\nBold: the largest IQM of the row.")


def pairwise_tex(result: StatsResult) -> str:
    pw = result.tables["pairwise"]
    if pw.empty:
        return ""
    keys = _keys(pw)
    header = keys + ["pair", "blocks", "median A", "median B", "Δ", "W–T–L", "Nemenyi p", "Wilcoxon–Holm p", "call"]
    rows, groups = [], []
    for rec in pw.to_dict("records"):
        a, b = value(rec["median_a"]), value(rec["median_b"])
        sign = 1.0 if rec["higher_is_better"] else -1.0
        if rec["median_a"] != rec["median_b"]:
            if sign * (rec["median_a"] - rec["median_b"]) > 0:
                a = rf"\textbf{{{a}}}"
            else:
                b = rf"\textbf{{{b}}}"
        call = "n.s." if not rec["significant"] else f"{label(rec['better'])} better"
        rows.append([escape(rec[k]) for k in keys]
                    + [f"{label(rec['a'])} vs {label(rec['b'])}", str(rec["n_blocks"]), a, b,
                       value(rec["median_diff"]), f"{rec['wins_a']}--{rec['ties']}--{rec['wins_b']}",
                       value(rec.get("p_nemenyi")), value(rec["p_holm"]), call])
        groups.append(tuple(rec[k] for k in keys))
    return tabular([escape(h) for h in header], rows, "l" * (len(keys) + 1) + "rrrrrrrl",
                   f"asp-dist stats: every pair of methods over the same blocks in the paired range "
                   f"({result.config.metric}).\nDelta = median paired difference A - B; W-T-L = blocks where A is "
                   "better, tied, worse; call: Friedman + Nemenyi\n(Wilcoxon with two methods) at alpha = "
                   f"{result.config.alpha}. Bold: the better median of the row.", _group_breaks(groups))


def improvement_tex(result: StatsResult) -> str:
    imp = result.tables.get("improvement", pd.DataFrame())
    if imp.empty:
        return ""
    keys = _keys(imp)
    header = keys + ["paired range", "pair", "blocks", "paired P", "runs", "unpaired P"]

    def cell(p: float, lo: float, hi: float) -> str:
        text = interval(p, lo, hi, 2)
        return bold_first(text) if lo > 0.5 or hi < 0.5 else text

    rows, groups = [], []
    for rec in imp.to_dict("records"):
        rows.append([escape(rec[k]) for k in keys]
                    + [escape(rec["paired_range"]), f"P({label(rec['a'])} $>$ {label(rec['b'])})",
                       str(rec["n_blocks"]),
                       cell(rec["poi_paired"], rec["poi_paired_ci_low"], rec["poi_paired_ci_high"]),
                       f"{rec['n_runs_a']}/{rec['n_runs_b']}", cell(rec["poi"], rec["poi_ci_low"], rec["poi_ci_high"])])
        groups.append(tuple(rec[k] for k in keys))
    return tabular([escape(h) for h in header], rows, "l" * (len(keys) + 2) + "rrrr",
                   "asp-dist stats: probability of improvement P(A > B) with its 95 % bootstrap interval, pooled "
                   "over the paired range;\npaired: over blocks (same base, data and initial weights), unpaired: "
                   "over runs (rliable's).\nBold: an interval entirely above or below 1/2 (a call).",
                   _group_breaks(groups))


BUILDERS: dict[str, Callable[[StatsResult], str]] = {
    "summary": summary_tex, "pairwise": pairwise_tex, "iqm": iqm_tex, "aggregate": aggregate_tex,
    "improvement": improvement_tex}


def write_latex_tables(result: StatsResult, out_dir: str | Path) -> dict[str, Path]:
    """stats/<name>.tex for every table of LATEX_TABLES that has rows; returns name -> path."""
    out = Path(out_dir) / "stats"
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for name in LATEX_TABLES:
        text = BUILDERS[name](result)
        if text:
            written[name] = write_atomic(out / f"{name}.tex", text)
    return written
