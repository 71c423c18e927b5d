"""What `asp-dist tune` searches, read from a space file's [tune] table, checked before anything runs (no Ray).

A tune space is a space (asp_dist.sweep.spaces) whose grid holds the calibration cells — one domain, its
methods, paired counts and calibration trials (ids 100–999; ids from 1000 on are for confirmatory runs) —
and a [tune] table::

    [tune]
    budget = 24              # configurations per method: the same for every method
    search = "tpe"           # tpe (Optuna's TPE, ray.tune.search.optuna) | random (Tune's random search)
    seed = 0                 # the searcher's seed: a tune run is reproducible
    metric = "mixed"         # the domain's metric the objective is the median of (its direction is the domain's)
    from_defaults = true     # configuration 0 of each method is its cells' own values (where inside the ranges)
    scheduler = "none"       # none: every configuration trains to its end | asha: ASHA stops hopeless ones early
    grace_points = 10        # asha: no configuration is stopped before this curve point (of ~50 per cell)
    reduction_factor = 3     # asha: rungs at grace_points · reduction_factor^k; past one go on only the best 1/3
    brackets = 1             # asha: its brackets (more than 1: which bracket a configuration gets is random)
    [tune.ranges]            # optional: narrow, widen or add a knob's range (asp_dist.knobs.Range)
    lr = { log_uniform = [3e-4, 3e-3] }
    [tune.knobs]             # optional: the knobs searched for a method (default: every knob with a range
    pc = ["lr"]              #   whose `needs` the method meets)

A configuration of a method is one value per searched knob. Its cells are the grid's cells of that method with
those values; its objective is the median of the metric over them (the method's own cells only: a method's
search never looks at another method's rows).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from asp_dist.core.registry import DOMAINS, get_domain
from asp_dist.errors import SpecError, SweepError
from asp_dist.hashing import stable_hash
from asp_dist.knobs import Range
from asp_dist.method_registry import get_method, method_order
from asp_dist.spec import FIELD_NAMES, SEARCH, CellSpec, field_type, shapes_base
from asp_dist.sweep.spaces import expand, read_space_toml, space_file

SEARCHES = ("tpe", "random")
SCHEDULERS = ("none", "asha")
ASHA_KEYS = ("grace_points", "reduction_factor", "brackets")
TUNE_KEYS = {"budget", "search", "seed", "metric", "from_defaults", "scheduler", *ASHA_KEYS, "ranges", "knobs"}
CALIBRATION_TRIALS = range(100, 1000)  # 1000 and up: confirmatory trials, never tuned on


@dataclass(frozen=True)
class TuneSettings:
    budget: int = 24
    search: str = "tpe"
    seed: int = 0
    metric: str = "mixed"
    from_defaults: bool = True
    scheduler: str = "none"      # "asha": ray.tune.schedulers.ASHAScheduler on the configurations' curve points
    grace_points: int = 10
    reduction_factor: float = 3.0
    brackets: int = 1

    def record(self) -> dict[str, Any]:
        """The settings as a tune run records and fingerprints them: without a scheduler, the settings of a run
        made before schedulers existed (so that it resumes), with ASHA its knobs too."""
        settings = dict(vars(self))
        if self.scheduler == "none":
            for key in ("scheduler", *ASHA_KEYS):
                del settings[key]
        return settings


@dataclass
class MethodSearch:
    """One method's search: its knobs' ranges and its cells at the space's settings (before tuning)."""

    method: str
    ranges: dict[str, Range]
    cells: list[CellSpec]

    def configuration(self, values: dict[str, Any]) -> list[CellSpec]:
        """The method's cells with `values` (one per searched knob), resolved."""
        return [cell.replace(**values).resolved() for cell in self.cells]

    def defaults(self) -> dict[str, Any] | None:
        """The searched knobs' values in the method's cells (the configuration it runs untuned), or None where
        one lies outside its range."""
        values = {k: getattr(self.cells[0], k) for k in self.ranges}
        return values if all(self.ranges[k].contains(v) for k, v in values.items()) else None


@dataclass
class TunePlan:
    name: str
    space: str
    domain: str
    settings: TuneSettings
    searches: dict[str, MethodSearch]
    higher_is_better: bool
    space_text: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def objective_column(self) -> str:
        return f"eval_{self.settings.metric}"

    def fingerprint(self) -> str:
        """What a resumed tune run must match: the settings, each method's ranges and cells."""
        return stable_hash({"settings": self.settings.record(),
                            "searches": {m: {"ranges": {k: r.to_toml() for k, r in s.ranges.items()},
                                             "cells": sorted(c.cell_id for c in s.cells)}
                                         for m, s in self.searches.items()}})[:16]

    @classmethod
    def from_space(cls, space: str, name: str | None = None) -> "TunePlan":
        path = space_file(space)
        text = path.read_text()
        table = read_space_toml(path).get("tune")
        label = f"tune space {path.stem}"
        if not isinstance(table, dict):
            raise SweepError(f"{label}: it has no [tune] table (budget, search, seed, metric, ranges); a space "
                             f"without one is a sweep's: asp-dist sweep {path.stem}")
        cells = expand(space)
        return cls.build(name or path.stem, path.stem, cells, table, label, text)

    @classmethod
    def build(cls, name: str, space: str, cells: list[CellSpec], table: dict[str, Any], label: str,
              text: str = "") -> "TunePlan":
        unknown = sorted(set(table) - TUNE_KEYS)
        if unknown:
            raise SweepError(f"{label}: unknown key(s) {', '.join(unknown)} in [tune]; allowed: "
                             f"{', '.join(sorted(TUNE_KEYS))}")
        settings = _settings(table, label)
        check_scheduler(settings, cells, label)
        domains = sorted({c.domain for c in cells})
        if len(domains) != 1:
            raise SweepError(f"{label}: a tune run searches one domain's methods, its grid has {', '.join(domains)}")
        domain = get_domain(domains[0])
        if settings.metric not in domain.metrics:
            raise SweepError(f"{label}: metric {settings.metric!r} is not one of {domain.name}'s "
                             f"({', '.join(domain.metrics)})")
        confirmatory = sorted({c.trial for c in cells if c.trial not in CALIBRATION_TRIALS})
        if confirmatory:
            raise SweepError(f"{label}: tune on calibration trials ({CALIBRATION_TRIALS.start}-"
                             f"{CALIBRATION_TRIALS.stop - 1}); its grid has trial(s) {_ids(confirmatory)}")
        ranges = _ranges(table.get("ranges", {}), cells[0], label)
        chosen = table.get("knobs", {})
        if not isinstance(chosen, dict):
            raise SweepError(f"{label}: [tune.knobs] maps a method to a list of knobs, got {chosen!r}")
        present = {c.method for c in cells}
        methods = [m for m in method_order() if m in present]  # the registry's order: pc, osp, asp, plugins
        odd = sorted(set(chosen) - set(methods))
        if odd:
            raise SweepError(f"{label}: [tune.knobs] names method(s) {', '.join(odd)} that its grid does not have")
        searches = {}
        for method in methods:
            own = _method_ranges(method, ranges, chosen.get(method), label)
            mine = [c for c in cells if c.method == method]
            varied = sorted(k for k in own if len({repr(getattr(c, k)) for c in mine}) > 1)
            if varied:
                raise SweepError(f"{label}: {', '.join(varied)} varies across {method}'s cells (a grid axis) and is "
                                 f"searched too; keep one")
            searches[method] = MethodSearch(method, own, mine)
        return cls(name, space, domain.name, settings, searches, domain.metrics[settings.metric].higher_is_better,
                   text)


def _ids(trials: list[int]) -> str:
    return ", ".join(map(str, trials[:5])) + (f" … ({len(trials)} in all)" if len(trials) > 5 else "")


def _settings(table: dict[str, Any], label: str) -> TuneSettings:
    defaults = TuneSettings()
    budget, search = table.get("budget", defaults.budget), table.get("search", defaults.search)
    seed, metric = table.get("seed", defaults.seed), table.get("metric", defaults.metric)
    from_defaults = table.get("from_defaults", defaults.from_defaults)
    if not isinstance(from_defaults, bool):
        raise SweepError(f"{label}: from_defaults must be true or false, got {from_defaults!r}")
    if not isinstance(budget, int) or isinstance(budget, bool) or budget < 1:
        raise SweepError(f"{label}: budget is the number of configurations per method, an integer >= 1; got {budget!r}")
    if search not in SEARCHES:
        raise SweepError(f"{label}: search must be one of {', '.join(SEARCHES)}, got {search!r}")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise SweepError(f"{label}: seed must be an integer >= 0, got {seed!r}")
    if not isinstance(metric, str):
        raise SweepError(f"{label}: metric must be a metric's name, got {metric!r}")
    scheduler = table.get("scheduler", defaults.scheduler)
    if scheduler not in SCHEDULERS:
        raise SweepError(f"{label}: scheduler must be one of {', '.join(SCHEDULERS)}, got {scheduler!r}")
    asha = {k: table.get(k, getattr(defaults, k)) for k in ASHA_KEYS}
    stray = [k for k in ASHA_KEYS if k in table and scheduler != "asha"]
    if stray:
        raise SweepError(f"{label}: {', '.join(stray)} {'is an ASHA setting' if len(stray) == 1 else 'are ASHA settings'}"
                         f', which needs scheduler = "asha"')
    for key in ("grace_points", "brackets"):
        if not isinstance(asha[key], int) or isinstance(asha[key], bool) or asha[key] < 1:
            raise SweepError(f"{label}: {key} must be an integer >= 1, got {asha[key]!r}")
    factor = asha["reduction_factor"]
    if not isinstance(factor, (int, float)) or isinstance(factor, bool) or not factor > 1 or factor == float("inf"):
        raise SweepError(f"{label}: reduction_factor must be a number above 1, got {factor!r}")
    return TuneSettings(budget, search, seed, metric, from_defaults, scheduler, asha["grace_points"], float(factor),
                        asha["brackets"])


def curve_points(train_steps: int) -> int:
    """How many learning-curve points a cell of `train_steps` updates records (asp_dist.training.records: one
    every train_steps // CURVE_POINTS updates, and one at the last)."""
    from asp_dist.training.records import CURVE_POINTS  # imports torch: only a run with ASHA asks

    every = max(1, train_steps // CURVE_POINTS)
    return train_steps // every + (1 if train_steps % every else 0)


def check_scheduler(settings: TuneSettings, cells: list[CellSpec], label: str) -> None:
    """ASHA's grace period is within the cells' curves: its rungs are curve points."""
    if settings.scheduler != "asha":
        return
    points = min(curve_points(c.resolved().train_steps) for c in cells)
    if settings.grace_points > points:
        raise SweepError(f"{label}: grace_points is {settings.grace_points}, beyond the {points} curve points a "
                         f"cell of this grid records")


def _ranges(declared: Any, sample: CellSpec, label: str) -> dict[str, Range]:
    """The knobs' declared ranges (spec.SEARCH), narrowed, widened or added by the space's [tune.ranges]; each
    range checked: its shape, a knob that does not shape the base, both ends (every choice) a valid value."""
    if not isinstance(declared, dict):
        raise SweepError(f"{label}: [tune.ranges] maps a knob to a range, got {declared!r}")
    own = {k.name for k in get_domain(sample.domain).knobs}
    any_domains = {k.name for d in DOMAINS.values() for k in d.knobs}
    ranges = {k: r for k, r in SEARCH.items() if k in own or k not in any_domains}  # common knobs and its own
    for name, raw in declared.items():
        if name not in FIELD_NAMES:
            raise SweepError(f"{label}: [tune.ranges] names {name!r}, which is no knob; `asp-dist fields` lists them")
        if shapes_base(name, f"{sample.domain}_") or name in ("method", "paired"):
            raise SweepError(f"{label}: {name} cannot be tuned: every configuration of a tune run adopts the same "
                             f"base and trains on the same cells")
        needs = ranges[name].needs if name in ranges else ()
        try:
            rng = Range.from_toml(name, raw, needs)
        except ValueError as e:
            raise SweepError(f"{label}: {e}") from None
        problems = rng.problems(name, field_type(name))
        if problems:
            raise SweepError(f"{label}: {problems[0]}")
        ends = rng.values if rng.kind == "choice" else (rng.low, rng.high)
        for value in ends:
            try:
                sample.replace(**{name: value}).resolved()
            except SpecError as e:
                raise SweepError(f"{label}: the range of {name} reaches {value!r}, which a cell refuses: {e}") from None
        ranges[name] = rng
    return ranges


def _method_ranges(method: str, ranges: dict[str, Range], chosen: Any, label: str) -> dict[str, Range]:
    """The ranges searched for `method`: the knobs [tune.knobs] names for it, else every knob with a range
    whose `needs` the method trains on."""
    terms = get_method(method)
    if chosen is None:
        own = {k: r for k, r in ranges.items() if all(getattr(terms, n) for n in r.needs)}
    else:
        if not isinstance(chosen, list) or not all(isinstance(k, str) for k in chosen):
            raise SweepError(f"{label}: [tune.knobs] {method} must be a list of knob names, got {chosen!r}")
        missing = [k for k in chosen if k not in ranges]
        if missing:
            raise SweepError(f"{label}: [tune.knobs] {method} names {', '.join(missing)}, which has no range "
                             f"(declare one in [tune.ranges])")
        own = {k: ranges[k] for k in chosen}
    if not own:
        raise SweepError(f"{label}: method {method} has nothing to tune (no knob with a range applies to it); "
                         f"declare one in [tune.ranges] or name its knobs in [tune.knobs]")
    return own


def winning_configuration(configurations, higher_is_better: bool):
    """The row of `configurations` (one method's rows of configurations.parquet) its search chooses: the best
    objective among the configurations that trained to their end (ASHA's stopped ones are never chosen), ties
    to the lowest configuration index; None when none has an objective. The one rule of tuned.toml, the
    tuning report and bench/asha_saving.py."""
    rows = configurations[configurations["objective"].notna()]
    if "stopped_early" in rows:
        rows = rows[~rows["stopped_early"].eq(True)]
    if rows.empty:
        return None
    rows = rows.sort_values("configuration", kind="stable")
    return rows.loc[rows["objective"].idxmax() if higher_is_better else rows["objective"].idxmin()]
