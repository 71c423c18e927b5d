"""`asp-dist tune`'s driver: both stages of a tune run, its tables and tuned.toml.

Under the sweep's lock: the plan record (a resumed run must match it), stage 1 (each method's search,
asp_dist.sweep.tuning), stage 2 when the plan has one (each method's candidates on the validation trials,
asp_dist.sweep.tune_validation), then `configurations.parquet` (every configuration of both stages: `stage`
"search" or "validation", `default`, `chosen`) and `tuned.toml` (each method's chosen setting, as a space's
[methods.<name>] settings). Without stage 2 (top_k = 0) a method's setting is its search's best.
"""

from __future__ import annotations

import json
import logging
import os
import sys
from dataclasses import dataclass
from typing import Any, TextIO

import pandas as pd
import pyarrow as pa

from asp_dist.errors import SweepError
from asp_dist.results.location import AnyPath, parquet_bytes, write_replace
from asp_dist.sweep import ledger, preflight, signals
from asp_dist.sweep.ray_host import ray_session
from asp_dist.sweep.tune_plan import TunePlan, winning_configuration
from asp_dist.sweep.tune_validation import candidates, run_validation, validation_table
from asp_dist.sweep.tuning import OBJECTIVE, _tuner, method_experiment, search_table, typed

PLAN_FILE = ledger.TUNE_PLAN_FILE     # in the run's directory: what a resumed run must match
CONFIGURATIONS = ledger.TUNE_CONFIGURATIONS
TUNED = "tuned.toml"


@dataclass
class TuneResult:
    name: str
    sweep_dir: AnyPath
    best: dict[str, dict[str, Any]]     # method -> {"values", "objective", "index", "default", "stage"}
    configurations: int


def _check_plan_record(sweep_dir: AnyPath, plan: TunePlan) -> None:
    """A tune run's directory holds the plan it was started with; another plan there is refused."""
    record = sweep_dir / PLAN_FILE
    fingerprint = plan.fingerprint()
    if record.exists():
        try:
            stored = json.loads(record.read_text())
        except (ValueError, UnicodeDecodeError):
            stored = None
        if not isinstance(stored, dict):
            raise SweepError(f"{record} is not the plan record asp-dist tune writes (unreadable JSON); give this run "
                             f"another --name, or restore the file")
        if stored.get("fingerprint") != fingerprint:
            raise SweepError(f"tune run {plan.name} was started with another plan (space {stored.get('space')}, "
                             f"settings {stored.get('settings')}); give this one another --name")
        return
    write_replace(record, json.dumps({"name": plan.name, "space": plan.space, "domain": plan.domain,
                                      "fingerprint": fingerprint, "settings": plan.settings.record(),
                                      "ranges": {m: {k: r.to_toml() for k, r in s.ranges.items()}
                                                 for m, s in plan.searches.items()}}, indent=1))



def chosen_settings(plan: TunePlan, table: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """Each method's chosen setting: stage 2's pick where the run has one, else its search's best."""
    best = {}
    for method, search in plan.searches.items():
        mine = table[table["method"] == method]
        validated = mine[mine["stage"] == "validation"]
        if len(validated):
            picked = validated[validated["chosen"]]
            row = picked.iloc[0] if len(picked) else None
        else:
            row = winning_configuration(mine, plan.higher_is_better)
        if row is None:
            continue
        index = row["configuration"]
        best[method] = {"index": None if pd.isna(index) else int(index), OBJECTIVE: float(row[OBJECTIVE]),
                        "default": bool(row.get("default", False)), "stage": row.get("stage", "search"),
                        "values": {k: typed(k, row[f"knob_{k}"]) for k in search.ranges}}
    return best


def _objective_words(plan: TunePlan) -> str:
    column = plan.objective_column
    if plan.settings.objective == "pooled_median":
        return f"median {column} over its cells"
    return f"the mean over paired counts of each count's median {column}"


def tuned_toml(plan: TunePlan, best: dict[str, dict[str, Any]]) -> str:
    """Each method's chosen setting as a space's [methods.<name>] settings, with where it was chosen."""
    settings = plan.settings
    search = f"search {settings.search}, budget {settings.budget}, seed {settings.seed}"
    if settings.top_k:
        trials = settings.validation_trials
        how = [f"# chosen on validation trials {trials[0]}-{trials[-1]} among its default and its {settings.top_k} best "
               f"search configurations", f"# ({_objective_words(plan)}; {search}, on the calibration trials)."]
    else:
        how = [f"# by its objective on the calibration trials ({_objective_words(plan)}; {search})."]
    if settings.scheduler == "asha":
        how.append(f"# {_asha(settings)}: a configuration it stopped is never chosen.")
    lines = [f"# asp-dist tune {plan.space} --name {plan.name}: each method's tuned setting,", *how,
             "# Use it as a space's settings:", f'#   settings = ["{plan.name}/tuned.toml"]', ""]
    for method, b in best.items():
        where = ("the default won validation" if b["default"] and b["stage"] == "validation" else
                 "its default" if b["default"] else f"configuration {b['index']}")
        stage = "validation objective" if b["stage"] == "validation" else "objective"
        lines.append(f"[methods.{method}]  # {where}, {stage} {b[OBJECTIVE]:.6g}")
        for key, value in b["values"].items():
            lines.append(f"{key} = {json.dumps(value)}")
        lines.append("")
    return "\n".join(lines)


def _asha(settings) -> str:
    """ASHA's settings in words, "" without it."""
    if settings.scheduler != "asha":
        return ""
    return (f"ASHA with grace_points {settings.grace_points}, reduction_factor {settings.reduction_factor:g}, "
            f"brackets {settings.brackets}")


def run_tune(plan: TunePlan, *, results: str, workers: int = 2, ray_temp_dir: str | None = None,
             checkpoint_every_s: float = 30.0, max_failures: int = 2, stream: TextIO | None = None) -> TuneResult:
    """Run (or continue) the tune run of `plan`; see the module docstring."""
    from asp_dist.sweep.tune import _fit

    logging.getLogger("ray.tune.analysis.experiment_analysis").setLevel(logging.ERROR)
    stream = stream or sys.stderr
    sweep_dir = ledger.sweep_dir_for(results, plan.name)
    os.environ.setdefault("TUNE_DISABLE_STRICT_METRIC_CHECKING", "1")  # a checkpoint's result has no objective yet
    settings = plan.settings
    with signals.sigterm_as_interrupt():
        if not (sweep_dir / PLAN_FILE).exists():  # a new tune run: the directory is free and writable
            preflight.check_sweep_dir(sweep_dir)
        with ledger.sweep_lock(sweep_dir):
            _check_plan_record(sweep_dir, plan)
            for method, search in plan.searches.items():
                start = ("its defaults first" if search.defaults() is not None else
                         "its defaults lie outside the ranges: all searched") if settings.from_defaults else ""
                stream.write(f"tune {plan.name}: {method}: {settings.budget} configurations of "
                             f"{', '.join(sorted(search.ranges))} over {len(search.cells)} cells each "
                             f"({settings.search}, seed {settings.seed}{', ' + start if start else ''}"
                             f"{', ' + _asha(settings) if _asha(settings) else ''})\n")
            with ray_session(workers, None, ray_temp_dir, stream=stream):
                for index, (method, search) in enumerate(plan.searches.items()):
                    experiment, done = method_experiment(sweep_dir, method, settings.budget)
                    if not done:
                        _fit(_tuner(plan, search, index, sweep_dir, workers, checkpoint_every_s, max_failures,
                                    experiment))
                    stream.write(f"tune {plan.name}: {method} done\n")
                table = search_table(plan, sweep_dir)
                if settings.top_k:
                    chosen = candidates(plan, table)
                    run_validation(plan, chosen, sweep_dir, workers, checkpoint_every_s, max_failures, stream)
                    table = pd.concat([table, validation_table(plan, chosen, sweep_dir)], ignore_index=True)
            best = chosen_settings(plan, table)
            table["chosen"] = [_is_chosen(row, best) for row in table.to_dict("records")]
            write_replace(sweep_dir / CONFIGURATIONS, parquet_bytes(pa.Table.from_pandas(table, preserve_index=False)))
            write_replace(sweep_dir / TUNED, tuned_toml(plan, best))
    if "stopped_early" in table:
        stopped = table[table["stopped_early"].eq(True)].groupby("method").size()
        stream.write(f"tune {plan.name}: ASHA stopped " + ", ".join(
            f"{stopped.get(m, 0)} of {settings.budget} {m} configurations" for m in plan.searches) + " early\n")
    for method, b in best.items():
        where = ("its default" if b["default"] else f"configuration {b['index']}")
        won = "won validation" if b["stage"] == "validation" else "best in the search"
        stream.write(f"tune {plan.name}: {method}: {where} {won} ({plan.objective_column} {b[OBJECTIVE]:.4g}): "
                     + ", ".join(f"{k}={v}" for k, v in b["values"].items()) + "\n")
    stream.write(f"tune {plan.name}: every configuration in {sweep_dir / CONFIGURATIONS}, the chosen ones in "
                 f"{sweep_dir / TUNED}; the cells' rows: asp-dist query {plan.name} --results {results}\n")
    return TuneResult(plan.name, sweep_dir, best, int((table["stage"] == "search").sum()))


def _is_chosen(row: dict[str, Any], best: dict[str, dict[str, Any]]) -> bool:
    """Whether a row of configurations.parquet is its method's chosen setting, in the stage that chose it."""
    b = best.get(row["method"])
    if b is None or row["stage"] != b["stage"]:
        return False
    if b["stage"] == "validation":
        return bool(row["chosen"])
    return not pd.isna(row["configuration"]) and int(row["configuration"]) == b["index"]
