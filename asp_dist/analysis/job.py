"""The stats job: rows of one or more sweeps -> every table, per domain, and the files they go to.

Of a tune run (`asp-dist tune`) the tables compare each method's tuned setting, not every configuration it tried
(tune_run_rows); the report's tuning section (tuning.py) shows those."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from asp_dist.analysis.completeness import completeness
from asp_dist.analysis.layout import DomainLayout, domain_layout, label_rows, metric_direction
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
from asp_dist.method_registry import COMPANION_LABEL
from asp_dist.results import store
from asp_dist.results.location import as_path
from asp_dist.results.query import DEFAULT_ORDER, Inputs, load_rows, open_inputs
from asp_dist.sweep.ledger import TUNE_CONFIGURATIONS as CONFIGURATIONS  # what asp-dist tune writes
from asp_dist.sweep.ledger import TUNE_PLAN_FILE as PLAN_FILE
from asp_dist.sweep.tune_plan import TuneSettings, winning_configuration

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
    tune_notes: list[str] = field(default_factory=list)  # per tune run: which of its rows the statistics compare


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
    rows, tune_notes = read_rows(inputs)
    result = compute(rows, cfg, inputs)
    result.tune_notes = tune_notes
    return result


def read_rows(inputs: Inputs) -> tuple[pd.DataFrame, list[str]]:
    """The inputs' rows that the statistics compare, sorted by the key columns, and a sentence per tune run: a
    sweep's rows all, a tune run's only its tuned settings' (tune_run_rows). A tune run's files are read apart from
    the others, so that only its own rows are narrowed, even where a sweep holds one of its cells."""
    runs = [d for d in inputs.sweep_dirs if is_tune_run(d)]
    if not runs:
        return load_rows(inputs), []
    cells = [store.cells_dir(d).resolve() for d in runs]
    groups: dict[int, list] = {}  # index into runs (-1: no tune run's) -> its files, in the inputs' order
    for f in inputs.files:
        groups.setdefault(next((i for i, c in enumerate(cells) if c in f.parents), -1), []).append(f)
    frames, notes = [], []
    for i, files in groups.items():
        rows = load_rows(replace(inputs, files=files))  # with the schema of all the inputs: the frames concatenate
        if i >= 0:
            rows, note = tune_run_rows(rows, runs[i])
            notes += [note] if note else []
        frames.append(rows)
    rows = pd.concat([f for f in frames if len(f)] or frames[:1], ignore_index=True)
    return rows.sort_values(list(DEFAULT_ORDER), kind="stable").reset_index(drop=True), notes


# ---- a tune run: each method's tuned setting, not every configuration ----------------------------------------
def is_tune_run(sweep_dir) -> bool:
    """Whether an input directory is a run of `asp-dist tune` (it has a configurations.parquet)."""
    return (as_path(sweep_dir) / CONFIGURATIONS).exists()


def read_tune_run(sweep_dir) -> tuple[pd.DataFrame, str, dict] | None:
    """A tune run's configurations.parquet, its domain and its settings (tune-plan.json); None for any other
    directory. The report's tuning section (tuning.py) reads it too."""
    path = as_path(sweep_dir) / CONFIGURATIONS
    if not path.exists():
        return None
    try:
        table = pd.read_parquet(str(path)) if isinstance(path, Path) else pd.read_parquet(path.open_input())
        plan = json.loads((as_path(sweep_dir) / PLAN_FILE).read_text())
        domain, settings = plan["domain"], plan.get("settings") or {}
    except (OSError, ValueError, KeyError, TypeError, AttributeError, pa.ArrowException) as err:
        raise SpecError(f"{sweep_dir} holds a {CONFIGURATIONS} or {PLAN_FILE} that cannot be read "
                        f"({type(err).__name__}); the tune run's files are damaged") from None
    return table, domain, settings


def tune_run_rows(rows: pd.DataFrame, sweep_dir) -> tuple[pd.DataFrame, str]:
    """The rows of one input (`rows`: every row read from `sweep_dir`) that the statistics compare, and a sentence
    saying which; a sweep's rows (no configurations.parquet) come back as they are, with "".

    Every configuration of a tune run has knob values of its own: read as a sweep's, each would be a condition or
    a treatment of its own, with nothing to compare it with. So of a tune run each method's tuned setting is kept,
    as tuned.toml has it (asp_dist.sweep.tune_run.chosen_settings), under its method's name: where the method was
    validated the candidate chosen (`chosen`), with its default candidate beside it as `<method>@default` where
    another one won (its companion: tables.default_vs_tuned_table); otherwise the search's winning configuration,
    in the direction of the rows' objective metric. The tuning section shows every configuration."""
    found = read_tune_run(sweep_dir)
    if found is None or "cell_id" not in rows or rows.empty:
        return rows, ""
    configs, _, settings = found
    validation = configs["stage"].eq("validation") if "stage" in configs else pd.Series(False, index=configs.index)
    validated, searched = configs[validation], configs[~validation]
    method_of: dict[str, str] = {}  # cell id -> the method its rows take in the statistics
    picks, higher = [], None
    for method in dict.fromkeys(configs["method"]):
        mine = validated[validated["method"] == method]
        if len(mine):  # the candidate chosen (none where the validation did not finish), its default beside it
            chosen = mine[_flag(mine, "chosen")]
            pick = chosen.iloc[0] if len(chosen) else None
            if pick is not None and not _flag(chosen, "default").iloc[0]:
                for ids in mine.loc[_flag(mine, "default"), "cell_ids"]:
                    method_of.update(dict.fromkeys(_split(ids), f"{method}@{COMPANION_LABEL}"))
        else:
            if higher is None:  # the objective's direction, as the rows say it
                higher = metric_direction(rows, f"eval_{settings.get('metric') or TuneSettings().metric}")
            pick = winning_configuration(searched[searched["method"] == method], higher)
        if pick is None:
            picks.append(f"{method.upper()} none")
            continue
        default = pick.get("default")  # a numpy bool, or NaN on a search row
        picks.append(f"{method.upper()} " + ("its default" if pd.api.types.is_bool(default) and default
                                              else _configuration(pick)))
        method_of.update(dict.fromkeys(_split(pick.get("cell_ids")), method))
    kept = rows[rows["cell_id"].isin(method_of)]
    kept = kept.assign(method=kept["cell_id"].map(method_of)).reset_index(drop=True)
    if len(validated):
        what = (f"a tune run: the statistics below compare each method's setting chosen on the validation trials "
                f"({', '.join(picks)}) and its default (`<method>@default`) where another setting won")
    else:
        what = (f"a tune run without a validation stage: the statistics below compare each method's best search "
                f"configuration ({', '.join(picks)}) on the rows that chose it (which flatter it)")
    return kept, (f"{as_path(sweep_dir).name} is {what}: {len(kept):,} of its {len(rows):,} rows. Every "
                  f"configuration is in the tuning section.")


def _flag(configs: pd.DataFrame, column: str) -> pd.Series:
    return configs[column].eq(True) if column in configs else pd.Series(False, index=configs.index)


def _split(cell_ids) -> list[str]:
    """configurations.parquet's `cell_ids` (comma-separated) as a list."""
    return [] if cell_ids is None or pd.isna(cell_ids) else [c for c in str(cell_ids).split(",") if c]


def _configuration(rec: pd.Series) -> str:
    index = rec.get("configuration")
    return "configuration " + ("–" if index is None or pd.isna(index) else str(int(index)))


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
