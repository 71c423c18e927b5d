"""GitHub Markdown tables from DataFrames, without an extra dependency (pandas' to_markdown needs tabulate)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import pandas as pd


def format_value(v: Any, digits: int = 4) -> str:
    """A table value as text, rounded as every table of the stats job rounds it (Markdown, HTML, LaTeX)."""
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "–"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.{digits - 1}e}"
        return f"{v:.{digits}g}"
    return str(v)


def format_cell(v: Any, digits: int = 4) -> str:
    """format_value, made safe inside a Markdown table cell."""
    return format_value(v, digits).replace("|", "\\|").replace("\n", " ")


def to_markdown(df: pd.DataFrame | None, columns: Sequence[str] | None = None) -> str:
    """A GitHub Markdown table of `columns` (those present, in that order; default all)."""
    if df is None or df.empty:
        return "_(none)_\n"
    cols = [c for c in (columns or df.columns) if c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for rec in df[cols].itertuples(index=False, name=None):
        lines.append("| " + " | ".join(format_cell(v) for v in rec) + " |")
    return "\n".join(lines) + "\n"
