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
    objective = "median_per_paired"  # a configuration's objective from its cells: the mean over paired counts of
                             #   each count's median (a setting that collapses at one count cannot win on the
                             #   others) | "pooled_median": the median over all its cells (runs before 2026-12-06)
    common_seeds = true      # every configuration of a method trains its cells with the same training and
                             #   evaluation seeds (the cells' common_seeds knob): configurations differ only in
                             #   their values, not in their draws (common random numbers)
    top_k = 3                # stage 2: each method's top_k search configurations and its default trained again on
                             #   the validation trials and chosen there (0: no stage 2, the search's best is chosen;
                             #   unset: 3, or budget - 1 where the budget is smaller)
    validation_trials = 20   # stage 2's trials: a count (the ids right after the calibration trials) or
                             #   { first = 400, last = 419 }; below 1000 and apart from the calibration trials
    [tune.ranges]            # optional: narrow, widen or add a knob's range (asp_dist.knobs.Range)
    lr = { log_uniform = [3e-4, 3e-3] }
    [tune.knobs]             # optional: the knobs searched for a method (default: every knob with a range
    pc = ["lr"]              #   whose `needs` the method meets)

A configuration of a method is one value per searched knob. Its cells are the grid's cells of that method with
those values; its objective aggregates the metric over them (`objective`; the method's own cells only: a
method's search never looks at another method's rows).

Two stages (docs/decisions/0058-tuning-chooses-on-validation-trials.md). Stage 1, the *search*, tries `budget`
configurations per method on the calibration trials. Stage 2, the *validation*, trains each method's default and
its `top_k` best search configurations (other than the default) on validation trials the search never saw, and
the method's tuned setting is the best there (ties to the default): the search's winner on a few trials is partly
its luck on their bases and seeds, and a default that no searched setting beats on fresh trials stays.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
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
OBJECTIVES = ("median_per_paired", "pooled_median")
TUNE_KEYS = {"budget", "search", "seed", "metric", "from_defaults", "scheduler", *ASHA_KEYS, "objective", "common_seeds",
             "top_k", "validation_trials", "ranges", "knobs"}
CALIBRATION_TRIALS = range(100, 1000)  # 1000 and up: confirmatory trials, never tuned on
# What a tune run did before the validation stage, common seeds and the per-paired objective (2026-12-06): a
# space that sets these runs as it did then, and its settings are recorded (and fingerprinted) as they were.
LEGACY = {"objective": "pooled_median", "common_seeds": False, "top_k": 0}


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
    objective: str = "median_per_paired"
    common_seeds: bool = True
    top_k: int = 3
    validation_trials: tuple[int, ...] = ()  # set by the plan: the ids stage 2 trains on (none when top_k is 0)

    def record(self) -> dict[str, Any]:
        """The settings as a tune run records and fingerprints them: without a scheduler, the settings of a run
        made before schedulers existed, and without the validation stage's settings where they are LEGACY's,
        those of a run made before it (so that such runs resume); otherwise every setting."""
        settings = dict(vars(self))
        if self.scheduler == "none":
            for key in ("scheduler", *ASHA_KEYS):
                del settings[key]
        for key, value in LEGACY.items():
            if settings[key] == value:
                del settings[key]
        if not self.top_k:
            del settings["validation_trials"]
        else:
            settings["validation_trials"] = list(self.validation_trials)
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

    validation_cells: list[CellSpec] = field(default_factory=list)  # stage 2's: the cells on the validation trials

    def default_values(self) -> dict[str, Any]:
        """The searched knobs' values in the method's cells: the configuration it runs untuned."""
        return {k: getattr(self.cells[0], k) for k in self.ranges}

    def defaults(self) -> dict[str, Any] | None:
        """The default values where every one lies inside its range (the search may start from them), else None."""
        values = self.default_values()
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
        if settings.common_seeds:  # the cells' own knob: their ids and seeds say that they share draws
            cells = [c.replace(common_seeds=True).resolved() for c in cells]
        if settings.top_k:
            settings = replace(settings, validation_trials=_validation_trials(table, cells, label))
        ranges = _ranges(table.get("ranges", {}), cells[0], label)
        chosen = table.get("knobs", {})
        if not isinstance(chosen, dict):
            raise SweepError(f"{label}: [tune.knobs] maps a method to a list of knobs, got {chosen!r}")
        present = {c.method for c in cells}
        arms = sorted(m for m in present if "@" in m)
        if arms:
            raise SweepError(f"{label}: a tune run searches methods, not arms ({', '.join(arms)}): its stage 2 already "
                             f"trains each method's default beside its best")
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
            searches[method] = MethodSearch(method, own, mine, _on_trials(mine, settings.validation_trials))
        return cls(name, space, domain.name, settings, searches, domain.metrics[settings.metric].higher_is_better,
                   text)


def _ids(trials: list[int]) -> str:
    return ", ".join(map(str, trials[:5])) + (f" … ({len(trials)} in all)" if len(trials) > 5 else "")


def _on_trials(cells: list[CellSpec], trials: tuple[int, ...]) -> list[CellSpec]:
    """The cells of `cells`' grid (every other knob as it is) on `trials` instead: stage 2's cells."""
    out: dict[str, CellSpec] = {}
    for cell in cells:
        for trial in trials:
            moved = cell.replace(trial=trial).resolved()
            out.setdefault(moved.cell_id, moved)
    return list(out.values())


def _validation_trials(table: dict[str, Any], cells: list[CellSpec], label: str) -> tuple[int, ...]:
    """Stage 2's trial ids: `validation_trials` as a count (the ids right after the calibration trials) or a
    {first, last} range; below 1000 and none of them a calibration trial."""
    raw = table.get("validation_trials", 20)
    calibration = sorted({c.trial for c in cells})
    if isinstance(raw, int) and not isinstance(raw, bool) and raw >= 1:
        ids = tuple(range(calibration[-1] + 1, calibration[-1] + 1 + raw))
    elif (isinstance(raw, dict) and set(raw) == {"first", "last"}
          and all(isinstance(v, int) and not isinstance(v, bool) for v in raw.values()) and raw["first"] <= raw["last"]):
        ids = tuple(range(raw["first"], raw["last"] + 1))
    else:
        raise SweepError(f"{label}: validation_trials is a number of trials (>= 1) or {{ first = A, last = B }} with "
                         f"A <= B; got {raw!r}")
    outside = [t for t in ids if t not in CALIBRATION_TRIALS]
    if outside:
        raise SweepError(f"{label}: validation trials must lie in {CALIBRATION_TRIALS.start}-"
                         f"{CALIBRATION_TRIALS.stop - 1} (1000 and up are confirmatory); they reach {_ids(outside)}"
                         f"{'; give them as { first = A, last = B }' if isinstance(raw, int) else ''}")
    shared = sorted(set(ids) & set(calibration))
    if shared:
        raise SweepError(f"{label}: validation trials {_ids(shared)} are calibration trials too; stage 2 must judge "
                         f"on trials the search did not see")
    return ids


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
    objective = table.get("objective", defaults.objective)
    if objective not in OBJECTIVES:
        raise SweepError(f"{label}: objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    common_seeds = table.get("common_seeds", defaults.common_seeds)
    if not isinstance(common_seeds, bool):
        raise SweepError(f"{label}: common_seeds must be true or false, got {common_seeds!r}")
    top_k = table.get("top_k", min(defaults.top_k, budget - 1))  # by default, as many as a small budget has
    if not isinstance(top_k, int) or isinstance(top_k, bool) or top_k < 0:
        raise SweepError(f"{label}: top_k is how many search configurations per method stage 2 validates, an "
                         f"integer >= 0 (0: no validation stage); got {top_k!r}")
    if top_k >= budget:
        raise SweepError(f"{label}: top_k ({top_k}) must be below the budget ({budget}): stage 2 validates the "
                         f"best few of a method's search, not all of it")
    if "validation_trials" in table and not top_k:
        raise SweepError(f"{label}: validation_trials is a stage-2 setting, which top_k = 0 turns off")
    return TuneSettings(budget, search, seed, metric, from_defaults, scheduler, asha["grace_points"], float(factor),
                        asha["brackets"], objective, common_seeds, top_k)


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


def configuration_objective(values: list[tuple[int, float]], rule: str) -> float:
    """A configuration's objective from its cells' (paired count, metric value) pairs, finite values only; NaN
    when there is none. median_per_paired: the mean over paired counts of each count's median, and NaN when a
    count the configuration trained has no value at all (every cell there failed: it is not judged on the rest);
    pooled_median: the median over every cell. Direction-free: the searcher is told the direction."""
    import math
    import statistics

    finite = [(p, v) for p, v in values if v is not None and math.isfinite(v)]
    if not finite:
        return float("nan")
    if rule == "pooled_median":
        return statistics.median(v for _, v in finite)
    counts = {p for p, _ in values}
    per_count = {p: [v for q, v in finite if q == p] for p in counts}
    if any(not vs for vs in per_count.values()):
        return float("nan")
    return statistics.fmean(statistics.median(vs) for vs in per_count.values())


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
