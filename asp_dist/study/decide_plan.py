"""What `asp-dist decide` registers, read from a space file's [decide] table and checked before anything runs.

A decide space is a space (asp_dist.sweep.spaces) whose grid holds the *largest* run the study allows — one
domain, the compared methods, the paired counts and a trial range { first, last } — and a [decide] table, the
pre-registered comparison::

    [decide]
    compare = ["asp vs osp", "asp vs pc"]  # the comparisons, each "A vs B" of the grid's methods (arms too);
                                           #   two-sided: a verdict says which is better, or that neither was shown
    metric = "eval_mixed"                  # the rows' column judged (its direction is the domain's)
    paired = { first = 2, last = 4 }       # the paired counts judged (default: all the grid's)
    test = "blocked-adastop"               # blocked-adastop | e-value (asp_dist.analysis.sequential)
    statistic = "mean"                     # a trial's score: the mean over its paired counts (mean) or of the
                                           #   treatments' within-block ranks (rank)
    alpha = 0.05                           # family-wise error rate over the comparisons
    beta = 0.0                             # blocked-adastop: power spent on stopping "equal" early (0: never)
    stage_trials = 10                      # trials added per stage; the grid's trial range is the maximum
    permutations = 10000                   # blocked-adastop: permutation draws
    seed = 0                               # the draws' seed

The sweep grows a stage at a time (stage s holds the grid's first s * stage_trials trials, through the same
--extend a user would run), the test looks after each stage, and it stops when every comparison is decided or
the grid's last trial has run. A method whose comparisons are all decided trains no later trial. The
registration and the grid are fingerprinted into the sweep's decide.json at its first stage: a changed [decide]
table or grid is refused in one line from then on.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from typing import Any

from asp_dist.analysis.sequential import STATISTICS, TESTS
from asp_dist.errors import SweepError
from asp_dist.hashing import stable_hash
from asp_dist.spec import CellSpec
from asp_dist.sweep.spaces import expand, grid_hash, read_space_toml, space_file, space_logging

DECIDE_KEYS = {"compare", "metric", "paired", "test", "statistic", "alpha", "beta", "stage_trials", "permutations",
               "seed"}
COMPARISON = re.compile(r"\s*(\S+)\s+vs\s+(\S+)\s*")


@dataclass(frozen=True)
class Registration:
    """The registered comparison, as the [decide] table says it (defaults filled in)."""

    compare: tuple[tuple[str, str], ...]
    metric: str = "eval_mixed"
    paired: tuple[int, int] | None = None
    test: str = "blocked-adastop"
    statistic: str = "mean"
    alpha: float = 0.05
    beta: float = 0.0
    stage_trials: int = 10
    permutations: int = 10_000
    seed: int = 0

    def record(self) -> dict[str, Any]:
        out = asdict(self)
        out["compare"] = [f"{a} vs {b}" for a, b in self.compare]
        out["paired"] = list(self.paired) if self.paired else None
        return out

    @property
    def treatments(self) -> list[str]:
        """The compared treatments, in order of first mention."""
        return list(dict.fromkeys(t for pair in self.compare for t in pair))


@dataclass(frozen=True)
class DecidePlan:
    name: str
    space: str            # the space file's stem
    registration: Registration
    domain: str
    specs: list[CellSpec]  # the whole grid: every stage's cells
    trials: tuple[int, ...]  # the grid's trial ids, ascending: stage s runs the first s * stage_trials
    space_text: str = ""
    logging: dict | None = None

    @property
    def stages(self) -> int:
        return looks_for(len(self.trials), self.registration.stage_trials)

    def stage_trials(self, stage: int) -> tuple[int, ...]:
        """The trial ids of stages 1..`stage`."""
        return self.trials[:min(stage * self.registration.stage_trials, len(self.trials))]

    def stage_specs(self, trained: list[set[str]]) -> list[CellSpec]:
        """The cells of stages 1..len(trained): stage s's new trials for the methods in trained[s - 1] (a method
        whose comparisons were all decided before stage s trains none of its trials)."""
        stage_of = {t: i // self.registration.stage_trials for i, t in enumerate(self.trials)}
        return [s for s in self.specs if stage_of[s.trial] < len(trained) and s.method in trained[stage_of[s.trial]]]

    def fingerprint(self) -> str:
        return stable_hash({"registration": self.registration.record(), "grid": grid_hash(self.specs)})[:16]

    @classmethod
    def from_space(cls, space: str, name: str | None = None) -> "DecidePlan":
        path = space_file(space)
        label = path.stem
        table = read_space_toml(path).get("decide")
        if table is None:
            raise SweepError(f"space {label} has no [decide] table: asp-dist decide needs a registered comparison "
                             f"(see docs/sweeps.md, 'Sequential verdicts'); run it with asp-dist sweep instead")
        specs = expand(space)
        return cls.build(name or label, label, specs, table, path.read_text(), space_logging(space))

    @classmethod
    def build(cls, name: str, space: str, specs: list[CellSpec], table: Any, space_text: str = "",
              logging: dict | None = None) -> "DecidePlan":
        label = f"space {space}: [decide]"
        if not isinstance(table, dict):
            raise SweepError(f"{label} must be a table, got {table!r}")
        unknown = sorted(set(table) - DECIDE_KEYS)
        if unknown:
            raise SweepError(f"{label} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(DECIDE_KEYS))}")
        domains = sorted({s.domain for s in specs})
        if len(domains) != 1:
            raise SweepError(f"space {space}: a decide space holds one domain, its grid has {', '.join(domains)}")
        reg = _registration(table, label)
        methods = sorted({s.method for s in specs})
        for t in reg.treatments:
            if t not in methods:
                raise SweepError(f"{label}: compare names {t!r}, which is not a method of the grid "
                                 f"({', '.join(methods)})")
        idle = [m for m in methods if m not in reg.treatments]
        if idle:
            raise SweepError(f"{label}: method(s) {', '.join(idle)} of the grid are in no comparison; their cells "
                             f"would train for nothing: compare them or leave them out of the grid")
        pairs = {(s.trial, s.paired, s.method) for s in specs}
        if len(pairs) != len(specs):
            raise SweepError(f"space {space}: a decide grid has one cell per (trial, paired, method); this one varies "
                             f"another knob too (one condition per registration)")
        trials = tuple(sorted({s.trial for s in specs}))
        if min(trials) < 1000:
            raise SweepError(f"space {space}: a decided verdict is confirmatory: its trials must be fresh ids from "
                             f"1000 on (the grid starts at {min(trials)})")
        paired = sorted({s.paired for s in specs})
        if reg.paired is not None and not any(reg.paired[0] <= p <= reg.paired[1] for p in paired):
            raise SweepError(f"{label}: paired {reg.paired[0]}-{reg.paired[1]} holds none of the grid's paired counts "
                             f"({', '.join(map(str, paired))})")
        if reg.stage_trials > len(trials):
            raise SweepError(f"{label}: stage_trials = {reg.stage_trials} is more than the grid's {len(trials)} trials")
        if reg.test == "blocked-adastop" and not first_look_can_decide(reg.stage_trials, len(trials), reg.alpha):
            looks = looks_for(len(trials), reg.stage_trials)
            least = next(n for n in range(2, 64) if first_look_can_decide(n, len(trials), reg.alpha))
            raise SweepError(f"{label}: stage_trials = {reg.stage_trials} cannot decide at the first look (its "
                             f"smallest p, 2/2^{reg.stage_trials}, is above alpha / {looks} looks); use at least "
                             f"{least}")
        return cls(name, space, reg, domains[0], specs, trials, space_text, logging or {})


def looks_for(trials: int, stage_trials: int) -> int:
    """The looks a registration plans: one after each stage, the last stage perhaps shorter."""
    return math.ceil(trials / stage_trials)


def first_look_can_decide(stage_trials: int, trials: int, alpha: float) -> bool:
    """Whether blocked-adastop's first look can pass: on n trials it has 2^n sign patterns, so its smallest
    two-sided p is 2 / 2^n, and the first look spends alpha / looks."""
    return 2.0 ** (1 - stage_trials) <= alpha / looks_for(trials, stage_trials)


def _number(table: dict, key: str, default, kind, lo, hi, label: str):
    value = table.get(key, default)
    if kind is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise SweepError(f"{label} {key} must be an integer, got {value!r}")
    if kind is float and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise SweepError(f"{label} {key} must be a number, got {value!r}")
    if not lo(value) or not hi(value):
        raise SweepError(f"{label} {key} = {value!r} is out of range")
    return kind(value)


def _registration(table: dict, label: str) -> Registration:
    compare = table.get("compare")
    if not isinstance(compare, list) or not compare or not all(isinstance(c, str) for c in compare):
        raise SweepError(f'{label} compare must be a non-empty list like ["asp vs osp", "asp vs pc"], got {compare!r}')
    pairs = []
    for text in compare:
        m = COMPARISON.fullmatch(text)
        if m is None or m.group(1) == m.group(2):
            raise SweepError(f'{label} compare entry {text!r} must read "A vs B" with two different methods')
        pair = (m.group(1), m.group(2))
        if pair in pairs or pair[::-1] in pairs:
            raise SweepError(f"{label} compares {pair[0]} and {pair[1]} twice")
        pairs.append(pair)
    metric = table.get("metric", "eval_mixed")
    if not isinstance(metric, str) or not metric:
        raise SweepError(f"{label} metric must be a column name like 'eval_mixed', got {metric!r}")
    paired = table.get("paired")
    if paired is not None:
        if (not isinstance(paired, dict) or set(paired) != {"first", "last"}
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in paired.values())
                or paired["last"] < paired["first"]):
            raise SweepError(f"{label} paired must be {{ first = INT, last = INT }} with first <= last, got {paired!r}")
        paired = (paired["first"], paired["last"])
    test = table.get("test", "blocked-adastop")
    if test not in TESTS:
        raise SweepError(f"{label} test must be one of {', '.join(TESTS)}, got {test!r}")
    statistic = table.get("statistic", "mean")
    if statistic not in STATISTICS:
        raise SweepError(f"{label} statistic must be one of {', '.join(STATISTICS)}, got {statistic!r}")
    alpha = _number(table, "alpha", 0.05, float, lambda v: v > 0, lambda v: v < 0.5, label)
    beta = _number(table, "beta", 0.0, float, lambda v: v >= 0, lambda v: v < 1, label)
    if beta and test != "blocked-adastop":
        raise SweepError(f"{label} beta (stopping 'equal' early) needs test = 'blocked-adastop'")
    stage = _number(table, "stage_trials", 10, int, lambda v: v >= 2, lambda v: True, label)
    perms = _number(table, "permutations", 10_000, int, lambda v: v >= 100, lambda v: v <= 1_000_000, label)
    seed = _number(table, "seed", 0, int, lambda v: v >= 0, lambda v: v < 2**32, label)
    return Registration(tuple(pairs), metric, paired, test, statistic, alpha, beta, stage, perms, seed)
