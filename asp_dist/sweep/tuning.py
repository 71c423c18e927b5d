"""`asp-dist tune`, stage 1: each method of a tune space searched with a Ray Tune search algorithm, on one budget.

(Stage 2, the validation of each method's best configurations, is asp_dist.sweep.tune_validation; the driver that
runs both and writes configurations.parquet and tuned.toml is asp_dist.sweep.tune_run.) For every method of the plan (asp_dist.sweep.tune_plan), in the space's order, one Tune experiment of
`budget` trials. A trial is one configuration (a value per searched knob): it trains the method's
calibration cells with those values — as one pack where the domain packs cells in sweeps (particles,
levers), else cell after cell — through the sweep's own unit function (asp_dist.sweep.trial.train_unit:
shared bases, checkpoints, rows and curves in the store, failures recorded), then reports its objective, the
domain's metric over its cells by the run's rule (tune_plan.configuration_objective; the rows in the store are
the truth it is read from).

The search: Optuna's TPE (ray.tune.search.optuna.OptunaSearch, seeded) by default, Tune's random search
(BasicVariantGenerator, seeded) as the control. TPE is asked in batches of `workers` configurations and told
their results together (ConcurrencyLimiter with batch=True), so what it suggests does not depend on which
configuration happens to finish first: a tune run with a seed is reproducible on any number of CPUs of
the same count.

Optionally (`scheduler = "asha"`), ASHA (ray.tune.schedulers.ASHAScheduler) stops hopeless configurations
early: while a configuration trains, each curve point that every one of its cells has closed and that carries
the cheap probe of the domain's metric (`probe_<metric>`, every 5th point and the last) is reported as
{objective: by the same rule, curve_point: its index from 1}, and ASHA compares configurations at its
rungs (curve points). A stopped configuration writes no row for the cells it was training (where the domain does
not pack, its cells train one after another and only the last one's points complete a report: the cells before
it keep their rows); it counts against its method's budget once, has no objective, is never chosen, and its
trial ends TERMINATED: never run again.

Resumable like a sweep: the lock is the sweep's. Tune's own state is never restored (Tuner.restore unpickles it,
and a results directory may be shared or copied: docs/decisions/0057-stored-artefacts-hold-no-code.md). Instead the
driver records each finished configuration as JSON (tune/records/<experiment>/<n>.json: its values and how it
ended); a method whose latest experiment has its whole budget recorded is done, and any other starts its search
again in a new experiment (tune-<method>-<k>). The seeded search suggests the same configurations for the same
results, and a configuration whose cells have rows trains nothing (the rows are the truth its objective is read
from), so the search runs through what was done in seconds and goes on where it stopped; a configuration that was
training when the run stopped starts its cells over, and one ASHA had stopped is trained and judged again.
`search_table` scores every configuration of a finished search from its records and rows.
"""

from __future__ import annotations

import json
import logging
import math
import re
import sys
from collections.abc import Callable
from typing import Any

from ray import tune

from asp_dist.errors import SweepError
from asp_dist.hashing import stable_hash
from asp_dist.knobs import Range
from asp_dist.results import store
from asp_dist.results.location import AnyPath, as_path, write_replace
from asp_dist.spec import CellSpec, field_type
from asp_dist.sweep.tune import _tune_result_logs
from asp_dist.sweep.tune_plan import MethodSearch, TunePlan, configuration_objective, curve_points
from asp_dist.sweep.tune_storage import TUNE_DIR, tune_storage

log = logging.getLogger(__name__)

OBJECTIVE = "objective"
CURVE_POINT = "curve_point"  # with ASHA: an intermediate result's curve point (from 1), ASHA's time_attr


# ---- a trial: one configuration ------------------------------------------------------------------------------
def configuration_units(search_cells: list[dict], values: dict[str, Any], method: str, sweep_dir: str,
                        sweep_id: str, checkpoint_every_s: float) -> list[dict[str, Any]]:
    """The units (asp_dist.sweep.trial) a configuration trains: one pack of all its cells where the domain's
    packed trainer takes them in sweeps, else one unit per cell. Names and pack ids follow from the cells, so
    a restarted trial finds its checkpoint."""
    from asp_dist.training import engines

    specs = [CellSpec.from_dict(d).replace(**values).resolved() for d in search_cells]
    ids = [s.cell_id for s in specs]
    common = {"sweep_dir": sweep_dir, "sweep_id": sweep_id, "checkpoint_every_s": checkpoint_every_s}
    if all(engines.sweep_packs(s) for s in specs) and len({engines.pack_key(s) for s in specs}) == 1:
        pack_id = f"{method}-{stable_hash(ids)[:10]}"
        return [{"name": pack_id, "pack_id": pack_id, "specs": [s.to_dict() for s in specs], "cell_ids": ids,
                 **common}]
    return [{"name": s.cell_id, "pack_id": None, "specs": [s.to_dict()], "cell_ids": [s.cell_id], **common}
            for s in specs]


def objective_of(sweep_dir: AnyPath, units: list[dict[str, Any]], column: str,
                 rule: str = "pooled_median") -> tuple[float, int]:
    """The objective of the units' cells, from their verified rows (tune_plan.configuration_objective: NaN when
    none has a row), and how many have one."""
    from asp_dist.results.location import parquet_file

    values: list[tuple[int, float | None]] = []
    for unit in units:
        for cell_id, spec in zip(unit["cell_ids"], unit["specs"]):
            value = None
            if store.is_done(sweep_dir, spec["domain"], spec["method"], cell_id):
                with parquet_file(store.cell_path(sweep_dir, spec["domain"], spec["method"], cell_id)) as f:
                    value = f.read(columns=[column]).column(0)[0].as_py()
            values.append((spec["paired"], value))
    done = sum(v is not None and math.isfinite(v) for _, v in values)
    return configuration_objective(values, rule), done


class CurveObjective:
    """With ASHA: a configuration's intermediate objective, from its cells' curve points as they close (the
    pipeline's on_points batches, asp_dist.training.pipeline.PointsFn). Once every cell has closed point i and
    at least one carries a finite `key` (probe_<metric>: every 5th point and the last), it reports
    {objective: those values by the run's objective rule (tune_plan.configuration_objective), curve_point: i + 1};
    each point once, in order. A cell that closes no more points (failed) holds the reports back: the
    configuration then trains to its end."""

    def __init__(self, cells: dict[str, int], key: str, report: Callable[[dict[str, Any]], None],
                 rule: str = "pooled_median"):
        self.key, self.report, self.rule = key, report, rule
        self.paired = dict(cells)  # cell id -> its paired count
        self.values: dict[str, list[float | None]] = {c: [] for c in cells}
        self.streamed = dict.fromkeys(cells, 0)  # points of each cell passed on by this run of its unit
        self.reported = 0  # points 0 .. reported-1 are done with

    def seed(self, cell_id: str, values: list[float | None]) -> None:
        """A cell's points as its stored curve holds them (a cell with a row is not trained again)."""
        self.values[cell_id] = list(values)

    def __call__(self, batch) -> None:
        for spec, points in batch:
            if spec.cell_id not in self.values:
                continue
            mine = self.values[spec.cell_id]
            for point in points:  # a restored unit passes its points on from its first: overwritten in place
                index, value = self.streamed[spec.cell_id], point.get(self.key)
                mine[index:index + 1] = [value]
                self.streamed[spec.cell_id] += 1
        self.flush()

    def flush(self) -> None:
        closed = min(len(v) for v in self.values.values())
        while self.reported < closed:
            i = self.reported
            self.reported += 1
            objective = configuration_objective([(self.paired[c], v[i]) for c, v in self.values.items()], self.rule)
            if not math.isnan(objective):
                self.report({OBJECTIVE: objective, CURVE_POINT: i + 1})


def _stored_curve(sweep_dir: AnyPath, spec: dict[str, Any], cell_id: str, key: str) -> list[float | None] | None:
    from asp_dist.results.location import parquet_file

    path = store.curve_path(sweep_dir, spec["domain"], spec["method"], cell_id)
    if not path.exists():
        return None
    with parquet_file(path) as f:
        return f.read(columns=[key]).column(0).to_pylist() if key in f.schema_arrow.names else None


def train_configuration(config: dict[str, Any], plan: dict[str, Any]) -> None:
    """The trainable: train one configuration's cells, then report its objective (with ASHA, also the
    intermediate objective at its curve points: CurveObjective)."""
    import torch

    from asp_dist.sweep.trial import train_unit

    torch.set_num_threads(1)
    values = {k: config[k] for k in plan["knobs"]}
    units = configuration_units(plan["cells"], values, plan["method"], plan["sweep_dir"], plan["sweep_id"],
                                plan["checkpoint_every_s"])

    def report(metrics: dict[str, Any], checkpoint=None) -> None:
        # Every result carries the objective (Tune's searchers read it from each); NaN until it is known. It
        # carries no curve_point: ASHA passes over a result without its time_attr, so no NaN reaches a rung.
        tune.report({**metrics, OBJECTIVE: float("nan")}, checkpoint=checkpoint)

    curve = None
    if plan.get("curve_key"):  # ASHA
        cells = {cid: spec["paired"] for unit in units for cid, spec in zip(unit["cell_ids"], unit["specs"])}
        curve = CurveObjective(cells, plan["curve_key"], tune.report, plan.get("objective", "pooled_median"))
        sweep_dir = as_path(plan["sweep_dir"])
        for unit in units:
            for cell_id, spec in zip(unit["cell_ids"], unit["specs"]):
                if store.is_done(sweep_dir, spec["domain"], spec["method"], cell_id):
                    stored = _stored_curve(sweep_dir, spec, cell_id, plan["curve_key"])
                    if stored is not None:
                        curve.seed(cell_id, stored)
    for unit in units:
        train_unit(unit, report, on_points=curve)
    cell_ids = [cid for unit in units for cid in unit["cell_ids"]]
    objective, done = objective_of(as_path(plan["sweep_dir"]), units, plan["column"],
                                   plan.get("objective", "pooled_median"))
    tune.report({OBJECTIVE: objective, "cells_done": done, "cells_failed": len(cell_ids) - done,
                 "cell_ids": ",".join(cell_ids)})


# ---- the driver --------------------------------------------------------------------------------------------
class TuneProgress(tune.Callback):
    """One line on stderr per finished configuration: the method's count against its budget, the objective,
    the best so far. Tune pickles its callbacks with the experiment: only the numbers are pickled."""

    def __init__(self, name: str, method: str, budget: int, higher_is_better: bool, records: str = "",
                 knobs: tuple[str, ...] = ()):
        self.name, self.method, self.budget, self.higher = name, method, budget, higher_is_better
        self.records, self.knobs = records, tuple(knobs)  # where each configuration's record goes (JSON)
        self.done, self.best = 0, None

    def __reduce__(self):
        return (TuneProgress, (self.name, self.method, self.budget, self.higher, self.records, self.knobs))

    def _record(self, trial, status: str) -> None:
        """The configuration's record: what configurations_table reads and what says the method is done."""
        if not self.records:
            return
        result = trial.last_result or {}
        kept = {k: result[k] for k in (OBJECTIVE, CURVE_POINT, "cells_done") if k in result}
        write_replace(as_path(self.records) / f"{_trial_number(trial)}.json",
                      json.dumps({"number": _trial_number(trial), "trial_id": trial.trial_id, "status": status,
                                  "values": {k: trial.config[k] for k in self.knobs}, "result": kept}))

    def on_trial_error(self, iteration, trials, trial, **info):
        self._record(trial, "ERROR")

    def on_trial_complete(self, iteration, trials, trial, **info):
        self._record(trial, "TERMINATED")
        result = trial.last_result or {}
        objective = result.get(OBJECTIVE, float("nan"))
        self.done = sum(t.status == "TERMINATED" or t is trial for t in trials)  # this one's status is set after
        if stopped_early(result):  # ASHA stopped it: its objective is an intermediate one, never the best
            last = f"last stopped by ASHA at curve point {result[CURVE_POINT]} (objective then {objective:.4g})"
        else:
            last = f"last objective {objective:.4g}"
            if not math.isnan(objective) and (self.best is None or (objective > self.best) == self.higher):
                self.best = objective
        best = "none yet" if self.best is None else f"{self.best:.4g}"
        print(f"tune {self.name}: {self.method} {self.done}/{self.budget} configurations, {last}, best {best}",
              file=sys.stderr, flush=True)


def stopped_early(result: dict[str, Any]) -> bool:
    """Whether a configuration's last result is an intermediate one (ASHA stopped it there): a finished
    configuration's last result is its final report, which counts its cells (cells_done) and has no curve point."""
    return CURVE_POINT in result and "cells_done" not in result



def search_space(ranges: dict[str, Range]) -> dict[str, Any]:
    """Tune's search space of a method's ranges."""
    space = {}
    for name, r in ranges.items():
        if r.kind == "log_uniform":
            space[name] = tune.loguniform(r.low, r.high)
        elif r.kind == "uniform":
            space[name] = tune.uniform(r.low, r.high)
        elif r.kind == "int":
            space[name] = tune.randint(r.low, r.high + 1)
        else:
            space[name] = tune.choice(list(r.values))
    return space


def _searcher(plan: TunePlan, method_index: int, workers: int, search: MethodSearch | None = None):
    """The search algorithm of one method, seeded from the plan's seed and the method's place; with
    from_defaults, its first configuration is the method's own values (`search`'s cells)."""
    seed = plan.settings.seed + 1009 * method_index
    mode = "max" if plan.higher_is_better else "min"
    start = search.defaults() if plan.settings.from_defaults and search is not None else None
    points = [start] if start is not None else None
    if plan.settings.search == "random":
        from ray.tune.search import BasicVariantGenerator

        return BasicVariantGenerator(points_to_evaluate=points, random_state=seed, max_concurrent=workers), mode
    import optuna
    from ray.tune.search import ConcurrencyLimiter
    from ray.tune.search.optuna import OptunaSearch

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.TPESampler(seed=seed)
    return ConcurrencyLimiter(OptunaSearch(points_to_evaluate=points, sampler=sampler, metric=OBJECTIVE, mode=mode),
                              max_concurrent=workers, batch=True), mode


def _scheduler(plan: TunePlan, search: MethodSearch):
    """ASHA on the configurations' curve points where the plan asks for it, else None (Tune's FIFO: every
    configuration trains to its end). Its rungs: grace_points · reduction_factor^k up to the cells' last curve
    point. It never stops a configuration for reaching the last point (stop_last_trials=False: the cells still
    have to be evaluated and written)."""
    settings = plan.settings
    if settings.scheduler != "asha":
        return None
    from ray.tune.schedulers import ASHAScheduler

    last = max(curve_points(c.resolved().train_steps) for c in search.cells)
    return ASHAScheduler(time_attr=CURVE_POINT, max_t=last, grace_period=settings.grace_points,
                         reduction_factor=settings.reduction_factor, brackets=settings.brackets, stop_last_trials=False)


RECORDS = "records"  # under the run's tune/: one folder of configuration records per Tune experiment


SEARCH, VALIDATION = "tune", "validate"  # the two stages' experiment names: tune-<method>, validate-all


def _experiment_name(method: str, k: int = 1, stage: str = SEARCH) -> str:
    """A method's k-th Tune experiment of a stage (a run stopped midway is run again in the next)."""
    return f"{stage}-{method}" if k == 1 else f"{stage}-{method}-{k}"


def _experiment_numbers(folder: AnyPath, method: str, stage: str = SEARCH) -> list[int]:
    """The k of every experiment of `method` and `stage` named in `folder` (Tune's tune/ or its records/)."""
    pattern = re.compile(rf"{stage}-{re.escape(method)}(?:-(\d+))?")
    try:
        names = [p.name for p in folder.iterdir()]
    except (FileNotFoundError, NotADirectoryError):
        return []
    return sorted(int(m.group(1) or 1) for m in map(pattern.fullmatch, names) if m)


def _records(sweep_dir: AnyPath, experiment: str) -> list[dict[str, Any]]:
    """The configuration records of one experiment, in the order Tune created the configurations. A record that
    is not what TuneProgress writes is one line (a results tree edited by hand), never a traceback."""
    folder = sweep_dir / TUNE_DIR / RECORDS / experiment
    try:
        paths = [p for p in folder.iterdir() if p.name.endswith(".json") and p.name[:-5].isdigit()]
    except (FileNotFoundError, NotADirectoryError):
        return []
    records = []
    for path in paths:
        try:
            record = json.loads(path.read_text())
            records.append((int(record["number"]), record["trial_id"], record["status"], dict(record["values"]),
                            dict(record["result"])))
        except (ValueError, KeyError, TypeError, UnicodeDecodeError):
            raise SweepError(f"{path} is not a configuration record asp-dist tune writes; remove the tune run's "
                             f"tune/{RECORDS}/{experiment}/ to search that method again") from None
    return [{"number": n, "trial_id": t, "status": st, "values": v, "result": r} for n, t, st, v, r in sorted(records)]


def method_experiment(sweep_dir: AnyPath, method: str, budget: int, stage: str = SEARCH) -> tuple[str, bool]:
    """The experiment of `method` and `stage` to read or run, and whether its whole budget is recorded (done).
    Else a new one: its number above every experiment of the method and stage that Tune or the records name."""
    recorded = _experiment_numbers(sweep_dir / TUNE_DIR / RECORDS, method, stage)
    if recorded and len(_records(sweep_dir, _experiment_name(method, recorded[-1], stage))) >= budget:
        return _experiment_name(method, recorded[-1], stage), True
    known = recorded + _experiment_numbers(sweep_dir / TUNE_DIR, method, stage)
    return _experiment_name(method, max(known, default=0) + 1, stage), False


def _tuner(plan: TunePlan, search: MethodSearch, index: int, sweep_dir: AnyPath, workers: int,
           checkpoint_every_s: float, max_failures: int, experiment: str) -> tune.Tuner:
    """A new Tune experiment of one method's whole search (never a restored one: see the module docstring)."""
    storage_path, storage_fs = tune_storage(sweep_dir)
    info = {"method": search.method, "knobs": sorted(search.ranges), "cells": [c.to_dict() for c in search.cells],
            "sweep_dir": str(sweep_dir), "sweep_id": plan.name, "checkpoint_every_s": checkpoint_every_s,
            "column": plan.objective_column, "higher_is_better": plan.higher_is_better,
            "objective": plan.settings.objective}
    if plan.settings.scheduler == "asha":
        info["curve_key"] = f"probe_{plan.settings.metric}"
    trainable = tune.with_resources(tune.with_parameters(train_configuration, plan=info), {"cpu": 1})
    searcher, mode = _searcher(plan, index, workers, search)
    records = str(sweep_dir / TUNE_DIR / RECORDS / experiment)
    return tune.Tuner(
        trainable, param_space=search_space(search.ranges),
        tune_config=tune.TuneConfig(search_alg=searcher, metric=OBJECTIVE, mode=mode, num_samples=plan.settings.budget,
                                    scheduler=_scheduler(plan, search),
                                    reuse_actors=True),  # the searcher limits concurrency to `workers`
        run_config=tune.RunConfig(name=experiment, storage_path=storage_path, storage_filesystem=storage_fs,
                                  verbose=0, failure_config=tune.FailureConfig(max_failures=max_failures),
                                  checkpoint_config=tune.CheckpointConfig(num_to_keep=1),
                                  callbacks=[TuneProgress(plan.name, search.method, plan.settings.budget,
                                                          plan.higher_is_better, records, tuple(sorted(search.ranges))),
                                             *_tune_result_logs()]))


def search_table(plan: TunePlan, sweep_dir: AnyPath):
    """Every configuration of each method's finished search (stage 1), from its records, scored from the rows;
    `default` marks the configurations whose values are the method's defaults."""
    import pandas as pd

    records = []
    for method, search in plan.searches.items():
        experiment, done = method_experiment(sweep_dir, method, plan.settings.budget)
        if not done:
            raise SweepError(f"tune run {plan.name}: the {method} search is not finished ({experiment}); run the same "
                             f"asp-dist tune command again to finish it")
        for index, trial in enumerate(_records(sweep_dir, experiment)):
            values = {k: trial["values"][k] for k in search.ranges}
            units = configuration_units([c.to_dict() for c in search.cells], values, method, str(sweep_dir),
                                        plan.name, 30.0)
            cell_ids = [cid for unit in units for cid in unit["cell_ids"]]
            objective, done = objective_of(sweep_dir, units, plan.objective_column, plan.settings.objective)
            record = {"method": method, "stage": "search", "configuration": index, "trial_id": trial["trial_id"],
                      "default": values == search.default_values(),
                      **{f"knob_{k}": v for k, v in values.items()}, OBJECTIVE: objective,
                      "cells": len(cell_ids), "cells_done": done, "cell_ids": ",".join(cell_ids)}
            if plan.settings.scheduler == "asha":
                # A stopped configuration has no objective (no rows of its own; another configuration of the same
                # values may have written them): its intermediate one and where ASHA stopped it instead.
                result = trial["result"]
                stopped = trial["status"] == "TERMINATED" and stopped_early(result)
                record.update({OBJECTIVE: float("nan") if stopped else objective, "stopped_early": stopped,
                               "stopped_at_point": int(result[CURVE_POINT]) if stopped else None,
                               "objective_at_stop": float(result[OBJECTIVE]) if stopped else None})
            records.append(record)
    table = pd.DataFrame.from_records(records)
    if "stopped_at_point" in table:
        table["stopped_at_point"] = table["stopped_at_point"].astype("Int64")
        table["objective_at_stop"] = table["objective_at_stop"].astype(float)
    return table


def typed(name: str, value: Any) -> Any:
    """A knob's value from a table as the field's own type (a column shared with other methods' NaN is float)."""
    value = value.item() if hasattr(value, "item") else value
    return field_type(name)(value)


def _trial_number(trial) -> int:
    """The order Tune created a trial in (its experiment tag starts with it: "3_lr=0.002"); trial ids are random."""
    return int(str(trial.experiment_tag).split("_", 1)[0])


