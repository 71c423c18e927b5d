"""Stage 2 of `asp-dist tune`: each method's tuned setting chosen on validation trials the search never saw.

The search (stage 1, asp_dist.sweep.tuning) ranks a method's configurations on a few calibration trials, and
its winner is partly the luck of their bases and of its own draws (docs/decisions/0058). Here each method's
*candidates*, its default (the knobs' values in its cells, searched or not) and its `top_k` best search
configurations other than the default, train again on the validation trials (tune_plan: `validation_trials`),
with the run's objective rule and seed rule, and the best of them there is the method's tuned setting; a tie
goes to the default, then to the better search rank. Every method validates the same number of candidates
where its search finished that many (`top_k` + 1), so the budget stays equal in both stages.

One Tune experiment for every method's candidates (validate-all, its trials a grid over them), run, recorded and
resumed as a search's is: a candidate whose cells have rows trains nothing, and the rows are what it is
scored from.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ray import tune

from asp_dist.results.location import AnyPath
from asp_dist.sweep.tune import _tune_result_logs
from asp_dist.sweep.tune_plan import MethodSearch, TunePlan, winning_configuration
from asp_dist.sweep.tune_storage import TUNE_DIR, tune_storage
from asp_dist.sweep.tuning import (
    OBJECTIVE,
    RECORDS,
    VALIDATION,
    TuneProgress,
    configuration_units,
    method_experiment,
    objective_of,
    train_configuration,
    typed,
)

ENTRY = "candidate"  # the validation experiment's one parameter: the candidate's place in its method's list


@dataclass(frozen=True)
class Candidate:
    method: str
    values: dict[str, Any]     # one per searched knob
    default: bool              # the method's default values
    configuration: int | None  # its index in the search; None: a default the search did not try
    search_objective: float    # its objective in the search (NaN where it has none)


def candidates(plan: TunePlan, search_rows) -> dict[str, list[Candidate]]:
    """Each method's candidates, in order: its default, then its best search configurations by objective (ties to
    the lower index) that are not the default and not a repeat of another candidate's values, `top_k` at most.
    Configurations ASHA stopped or that have no objective are never candidates."""
    out = {}
    for method, search in plan.searches.items():
        rows = search_rows[search_rows["method"] == method]
        default_values = search.default_values()
        tried = rows[rows["default"]] if "default" in rows else rows.iloc[:0]
        first = tried.iloc[0] if len(tried) else None
        chosen = [Candidate(method, default_values, True, None if first is None else int(first["configuration"]),
                            float("nan") if first is None else float(first[OBJECTIVE]))]
        left = rows
        while len(chosen) <= plan.settings.top_k:
            best = winning_configuration(left, plan.higher_is_better)
            if best is None:
                break
            left = left[left["configuration"] != best["configuration"]]
            values = {k: typed(k, best[f"knob_{k}"]) for k in search.ranges}
            if any(values == c.values for c in chosen):
                continue
            chosen.append(Candidate(method, values, False, int(best["configuration"]), float(best[OBJECTIVE])))
        out[method] = chosen
    return out


def validation_units(plan: TunePlan, search: MethodSearch, candidate: Candidate, sweep_dir: AnyPath,
                     checkpoint_every_s: float = 30.0) -> list[dict[str, Any]]:
    return configuration_units([c.to_dict() for c in search.validation_cells], candidate.values, search.method,
                               str(sweep_dir), plan.name, checkpoint_every_s)


def validate_candidate(config: dict[str, Any], entries: list[dict[str, Any]]) -> None:
    """The trainable: train one candidate's validation cells (the search's trainable, with its values)."""
    entry = entries[config[ENTRY]]
    train_configuration(entry["values"], entry["plan"])


ALL = "all"  # the one validation experiment's name: validate-all (every method's candidates)


def _entry(plan: TunePlan, search: MethodSearch, candidate: Candidate, sweep_dir: AnyPath,
           checkpoint_every_s: float) -> dict[str, Any]:
    """What the trainable needs of one candidate: its values and the search's trainable's plan, on stage 2's cells."""
    return {"values": candidate.values, "plan": {
        "method": search.method, "knobs": sorted(search.ranges), "cells": [c.to_dict() for c in search.validation_cells],
        "sweep_dir": str(sweep_dir), "sweep_id": plan.name, "checkpoint_every_s": checkpoint_every_s,
        "column": plan.objective_column, "higher_is_better": plan.higher_is_better,
        "objective": plan.settings.objective}}


def validation_tuner(plan: TunePlan, chosen: dict[str, list[Candidate]], sweep_dir: AnyPath, workers: int,
                     checkpoint_every_s: float, max_failures: int, experiment: str) -> tune.Tuner:
    """A new Tune experiment training every method's candidates on the validation trials: one experiment, so that
    the workers stay busy across methods (a method's few candidates would leave one idle at its end)."""
    storage_path, storage_fs = tune_storage(sweep_dir)
    entries = [_entry(plan, plan.searches[m], c, sweep_dir, checkpoint_every_s) for m in plan.searches for c in chosen[m]]
    trainable = tune.with_resources(tune.with_parameters(validate_candidate, entries=entries), {"cpu": 1})
    records = str(sweep_dir / TUNE_DIR / RECORDS / experiment)
    return tune.Tuner(
        trainable, param_space={ENTRY: tune.grid_search(list(range(len(entries))))},
        tune_config=tune.TuneConfig(max_concurrent_trials=workers, reuse_actors=True),
        run_config=tune.RunConfig(name=experiment, storage_path=storage_path, storage_filesystem=storage_fs,
                                  verbose=0, failure_config=tune.FailureConfig(max_failures=max_failures),
                                  checkpoint_config=tune.CheckpointConfig(num_to_keep=1),
                                  callbacks=[TuneProgress(plan.name, "validation", len(entries),
                                                          plan.higher_is_better, records, (ENTRY,)),
                                             *_tune_result_logs()]))


def run_validation(plan: TunePlan, chosen: dict[str, list[Candidate]], sweep_dir: AnyPath, workers: int,
                   checkpoint_every_s: float, max_failures: int, stream) -> None:
    """Train every method's candidates on the validation trials, unless the validation is recorded whole."""
    from asp_dist.sweep.tune import _fit

    trials = plan.settings.validation_trials
    total = sum(len(c) for c in chosen.values())
    experiment, done = method_experiment(sweep_dir, ALL, total, VALIDATION)
    if not done:
        for method, search in plan.searches.items():
            stream.write(f"tune {plan.name}: {method}: validating {len(chosen[method])} configurations (its default "
                         f"and its best {len(chosen[method]) - 1}) on trials {trials[0]}-{trials[-1]}, "
                         f"{len(search.validation_cells)} cells each\n")
        _fit(validation_tuner(plan, chosen, sweep_dir, workers, checkpoint_every_s, max_failures, experiment))
    stream.write(f"tune {plan.name}: validation done\n")


def validation_table(plan: TunePlan, chosen: dict[str, list[Candidate]], sweep_dir: AnyPath):
    """Stage 2's rows of configurations.parquet: every candidate with its validation objective (from the rows of its
    validation cells) and `chosen`, the method's tuned setting."""
    import pandas as pd

    records = []
    for method, search in plan.searches.items():
        for order, candidate in enumerate(chosen[method]):
            units = validation_units(plan, search, candidate, sweep_dir)
            cell_ids = [cid for unit in units for cid in unit["cell_ids"]]
            objective, done = objective_of(sweep_dir, units, plan.objective_column, plan.settings.objective)
            records.append({"method": method, "stage": "validation", "configuration": candidate.configuration,
                            "candidate": order, "default": candidate.default,
                            **{f"knob_{k}": v for k, v in candidate.values.items()}, OBJECTIVE: objective,
                            "search_objective": candidate.search_objective, "cells": len(cell_ids),
                            "cells_done": done, "cell_ids": ",".join(cell_ids)})
    table = pd.DataFrame.from_records(records)
    table["configuration"] = table["configuration"].astype("Int64")
    winners = set()
    for method in plan.searches:
        # winning_configuration breaks ties to the lowest "configuration": here the candidate's order, default first
        mine = table[table["method"] == method].assign(configuration=lambda t: t["candidate"])
        best = winning_configuration(mine, plan.higher_is_better)
        if best is not None:
            winners.add((method, int(best["candidate"])))
    table["chosen"] = [(m, c) in winners for m, c in zip(table["method"], table["candidate"])]
    return table
