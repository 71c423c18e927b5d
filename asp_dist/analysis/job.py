"""The stats job: rows of one or more sweeps -> every table, per domain, and the files they go to."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from asp_dist.analysis.completeness import completeness
from asp_dist.analysis.layout import DomainLayout, domain_layout, label_rows
from asp_dist.analysis.markdown import to_markdown
from asp_dist.analysis.rliable_view import TABLES as RLIABLE_TABLES
from asp_dist.analysis.rliable_view import rliable_tables
from asp_dist.analysis.tables import (
    StatsConfig,
    by_paired_table,
    claim_2n_table,
    default_vs_tuned_table,
    efficiency_table,
    knob_trends,
    rank_tests,
    summary_table,
    threshold_for,
)
from asp_dist.errors import SpecError
from asp_dist.results.query import Inputs, load_rows, open_inputs

RANK_TABLES = ("summary", "tests", "pairwise", "by_paired", "efficiency", "claim_2n", "knob_trend",
               "default_vs_tuned")
TABLES = RANK_TABLES + ("missing",) + RLIABLE_TABLES


@dataclass
class StatsResult:
    config: StatsConfig
    rows: pd.DataFrame  # deduplicated rows with added columns: condition, treatment, score
    layouts: dict[str, DomainLayout]
    tables: dict[str, pd.DataFrame]  # one per name in TABLES (the rliable view's: rliable_view.py)
    inputs: Inputs | None = None
    notes: list[str] = field(default_factory=list)
    grid_known: bool = False  # every input sweep had a readable manifest.json and every file lies in one


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
    parts: dict[str, list[pd.DataFrame]] = {name: [] for name in RANK_TABLES}
    for domain, g in rows.groupby("domain", sort=True):
        layout = domain_layout(g, cfg.metric)
        layouts[domain] = layout
        g = label_rows(g, layout, cfg.metric)
        labelled.append(g)
        summary = summary_table(g, cfg, layout)
        omnibus, pairwise = rank_tests(g, cfg, layout)
        parts["summary"].append(summary)
        parts["tests"].append(pd.DataFrame(omnibus))
        parts["pairwise"].append(pd.DataFrame(pairwise))
        parts["by_paired"].append(pd.DataFrame(by_paired_table(g, cfg, layout)))
        threshold = threshold_for(g, cfg, layout, summary)
        parts["efficiency"].append(pd.DataFrame(efficiency_table(summary, threshold, cfg, layout)))
        parts["claim_2n"].append(pd.DataFrame(claim_2n_table(g, cfg, layout)))
        parts["knob_trend"].append(pd.DataFrame(knob_trends(g, cfg, layout)))
        parts["default_vs_tuned"].append(pd.DataFrame(default_vs_tuned_table(g, cfg, layout)))
    all_rows = pd.concat(labelled, ignore_index=True)
    tables = {name: _concat(dfs) for name, dfs in parts.items()}
    tables["missing"], more, grid_known = completeness(all_rows, inputs, layouts)
    tables.update(rliable_tables(all_rows, cfg, layouts, tables["pairwise"]))
    return StatsResult(cfg, all_rows, layouts, tables, inputs, more + notes, grid_known)


def _concat(dfs: list[pd.DataFrame]) -> pd.DataFrame:
    present = [df for df in dfs if not df.empty]
    return pd.concat(present, ignore_index=True) if present else pd.DataFrame()


def run_stats(paths: Sequence[str | Path], cfg: StatsConfig | None = None) -> StatsResult:
    """Read the rows behind sweep directories, directories or .parquet files, and compute every table."""
    inputs = open_inputs(paths)
    return compute(load_rows(inputs), cfg, inputs)


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
