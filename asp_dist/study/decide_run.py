"""`asp-dist decide`'s driver: grow a sweep stage by stage until its registered comparisons are decided.

Each stage is an ordinary sweep run (asp_dist.sweep.tune.run_plan) of the grid's first s * stage_trials trials,
grown with --extend; after it the registered test (asp_dist.analysis.sequential) looks at every stage's rows and
its look is appended to the sweep's decide.json. The test is recomputed from the rows at every look and must
reproduce each recorded earlier look: a look is never redrawn, and rows that changed under a recorded look are
refused. Killed inside a stage, the next run continues that stage's sweep (finished cells are kept); killed
between stages, it starts the next one. A method whose comparisons are all decided trains no later trial.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np
import pandas as pd

from asp_dist.analysis.sequential import CONTINUE, LARGER, SMALLER, SequentialResult, label, run_test, trial_scores
from asp_dist.errors import SweepError
from asp_dist.results import store
from asp_dist.results.location import AnyPath, write_replace
from asp_dist.spec import CellSpec
from asp_dist.study.decide_plan import DecidePlan
from asp_dist.sweep import ledger
from asp_dist.sweep.plan import Plan, RunOptions

DECIDE_FILE = ledger.DECIDE_FILE


@dataclass
class DecideResult:
    name: str
    sweep_dir: AnyPath
    looks: list[dict[str, Any]]
    finished: bool          # every comparison decided, or the grid's last trial run
    complete: bool          # every started stage's cells have rows (False: a cell failed; run again)


def read_record(sweep_dir: AnyPath) -> dict[str, Any] | None:
    """The sweep's decide.json (None: no stage has been judged yet); unreadable is refused in one line."""
    path = sweep_dir / DECIDE_FILE
    if not path.exists():
        return None
    try:
        record = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError):
        record = None
    if not isinstance(record, dict) or not isinstance(record.get("looks"), list):
        raise SweepError(f"{path} is not the record asp-dist decide writes (unreadable); restore it, or give this "
                         f"run another --name")
    return record


def check_record(plan: DecidePlan, record: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The recorded looks, after checking the record is this registration's (a changed one is refused)."""
    if record is None:
        return []
    if record.get("fingerprint") != plan.fingerprint():
        was = record.get("registration", {})
        raise SweepError(f"sweep {plan.name} was registered with another [decide] table or grid (compare "
                         f"{', '.join(was.get('compare', []))}; stage_trials {was.get('stage_trials')}; grid "
                         f"{record.get('grid_cells')} cells): a registration cannot change once a stage has run; "
                         f"restore the space or give this one another --name")
    return list(record["looks"])


def open_treatments(plan: DecidePlan, looks: list[dict[str, Any]]) -> set[str]:
    """The treatments of the comparisons still open after the last look (all before the first)."""
    decision = looks[-1]["decision"] if looks else {}
    return {t for pair in plan.registration.compare for t in pair if decision.get(label(pair), CONTINUE) == CONTINUE}


def is_finished(plan: DecidePlan, looks: list[dict[str, Any]]) -> bool:
    """Whether the recorded looks end the run: every comparison decided, or the last stage judged."""
    return bool(looks) and (looks[-1]["stage"] >= plan.stages
                            or all(d != CONTINUE for d in looks[-1]["decision"].values()))


def cells_through(plan: DecidePlan, looks: list[dict[str, Any]], next_stage: bool) -> list[CellSpec]:
    """The cells of the stages the looks judged, and with `next_stage` of the stage after them (what its
    sweep's manifest holds): a stage trains the treatments still open when it starts."""
    trained = [set(look["trained"]) for look in looks]
    return plan.stage_specs(trained + [open_treatments(plan, looks)] if next_stage else trained)


def stage_scores(plan: DecidePlan, rows: pd.DataFrame, stage: int) -> np.ndarray:
    """trials x treatments scores of stages 1..`stage` (NaN: a treatment a trial did not train), from the rows."""
    from asp_dist.analysis.layout import metric_direction

    reg = plan.registration
    trials = plan.stage_trials(stage)
    treatments = reg.treatments
    rows = rows[(rows["domain"] == plan.domain) & rows["method"].isin(treatments) & rows["trial"].isin(trials)]
    if reg.paired is not None:
        rows = rows[(rows["paired"] >= reg.paired[0]) & (rows["paired"] <= reg.paired[1])]
    if reg.metric not in rows:
        raise SweepError(f"[decide] metric {reg.metric!r} is not a column of the rows of sweep {plan.name}")
    paired = sorted({s.paired for s in plan.specs
                     if reg.paired is None or reg.paired[0] <= s.paired <= reg.paired[1]})
    sign = 1.0 if metric_direction(rows, reg.metric) else -1.0
    values = pd.to_numeric(rows[reg.metric], errors="coerce").astype(float) * sign
    cube = (pd.DataFrame({"trial": rows["trial"], "paired": rows["paired"], "method": rows["method"], "score": values})
            .pivot_table(index=["trial", "paired"], columns="method", values="score", aggfunc="mean")
            .reindex(index=pd.MultiIndex.from_product([trials, paired], names=["trial", "paired"]),
                     columns=treatments))
    blocks = cube.to_numpy().reshape(len(trials), len(paired), len(treatments))
    partial = np.isnan(blocks).any(axis=1) & ~np.isnan(blocks).all(axis=1)
    if partial.any():
        t, m = map(int, np.argwhere(partial)[0])
        raise SweepError(f"sweep {plan.name}: trial {trials[t]} of {treatments[m]} lacks a paired count's row "
                         f"({reg.metric} missing or not a number); asp-dist status {plan.name} shows its cells")
    return trial_scores(blocks, reg.statistic)


def stage_gaps(sweep_dir: AnyPath, specs: list[CellSpec]) -> tuple[list[int], list[CellSpec]]:
    """(lost trials, the other cells still without a row) of a stage's cells. A trial is lost when its base met
    no bar: every one of its cells failed with BaseRejected, which a retry repeats (the same seeds train the same
    attempts). As in every study of the project a lost trial counts toward its stage and enters no comparison
    (sequential.py: blocked-adastop adds zero for it in every draw, the e-value bets nothing on it)."""
    done, failed = ledger.finished_and_failed(sweep_dir, [s.cell_id for s in specs])
    records = store.failed_cells(sweep_dir) if failed else {}
    cells: dict[int, list[str]] = {}
    for spec in specs:
        cells.setdefault(spec.trial, []).append(spec.cell_id)
    lost = sorted(t for t, ids in cells.items() if all(c in failed and store.is_base_rejection(records[c]) for c in ids))
    return lost, [s for s in specs if s.cell_id not in done and s.trial not in lost]


def judge(plan: DecidePlan, rows: pd.DataFrame, stage: int) -> SequentialResult:
    """The registered test on the rows of stages 1..`stage`, looking after each stage."""
    reg = plan.registration
    y = stage_scores(plan, rows, stage)
    looks = [len(plan.stage_trials(s)) for s in range(1, stage + 1)]
    return run_test(reg.test, y, looks, reg.compare, reg.treatments, plan.stages, reg.alpha, reg.beta,
                    reg.permutations, reg.seed)


def _look_record(plan: DecidePlan, stage: int, look, trained: list[str]) -> dict[str, Any]:
    trials = plan.stage_trials(stage)
    return {"stage": stage, "trials": look.trials, "first_trial": trials[0], "last_trial": trials[-1],
            "trained": trained, **{k: v for k, v in look.as_dict().items() if k != "trials"}}


def _same(recorded: dict[str, Any], now: dict[str, Any]) -> bool:
    """Whether a recomputed look equals its record (decisions exactly, statistics to float precision)."""
    if recorded.get("decision") != now["decision"] or recorded.get("trials") != now["trials"]:
        return False
    old = recorded.get("statistic", {})
    return all(np.isclose(np.nan if old.get(k) is None else old[k], np.nan if v is None else v, equal_nan=True)
               for k, v in now["statistic"].items())


def _write(sweep_dir: AnyPath, plan: DecidePlan, looks: list[dict[str, Any]], finished: bool) -> None:
    record = {"name": plan.name, "space": plan.space, "domain": plan.domain, "fingerprint": plan.fingerprint(),
              "registration": plan.registration.record(), "grid_cells": len(plan.specs),
              "max_trials": len(plan.trials), "stages": plan.stages, "looks": looks, "finished": finished}
    write_replace(sweep_dir / DECIDE_FILE, json.dumps(record, indent=1))


def _fmt(value: float | None) -> str:
    return "none reached yet" if value is None else f"{value:.4g}"


def describe(decision: str, comparison: str) -> str:
    a, _, b = comparison.partition(" vs ")
    return {LARGER: f"{a} better than {b}", SMALLER: f"{b} better than {a}",
            CONTINUE: f"{comparison}: open"}.get(decision, f"{comparison}: no difference shown")


def run_decide(plan: DecidePlan, options: RunOptions, stream: TextIO | None = None, stop_after: int | None = None,
               runner=None) -> DecideResult:
    """Run (or continue) the decided sweep of `plan`; at most `stop_after` more stages (None: to the end).
    `runner` stands for asp_dist.sweep.tune.run_plan (tests)."""
    from asp_dist.sweep.preflight import check_can_start

    if runner is None:
        from asp_dist.sweep.tune import run_plan as runner
    stream = stream or sys.stderr
    sweep_dir = ledger.sweep_dir_for(options.results, plan.name)
    looks = check_record(plan, read_record(sweep_dir))
    reg = plan.registration
    ran = 0
    finished = is_finished(plan, looks)
    while not finished:
        stage = len(looks) + 1
        if stop_after is not None and ran >= stop_after:
            break
        needed = open_treatments(plan, looks)
        specs = cells_through(plan, looks, next_stage=True)
        trials = plan.stage_trials(stage)
        stream.write(f"decide {plan.name}: stage {stage} of at most {plan.stages}: trials {trials[0]}-{trials[-1]} "
                     f"({len(trials)} of {len(plan.trials)}), {', '.join(t for t in reg.treatments if t in needed)}\n")
        stage_plan = Plan(plan.name, plan.space, specs, plan.space_text, plan.logging or {})
        manifest = check_can_start(options.results, plan.name, specs, plan.space, options.pack, options.pack_size,
                                   extend=True)
        result = runner(dataclasses.replace(stage_plan, manifest=manifest), dataclasses.replace(options, extend=True),
                        stream)
        ran += 1
        lost, missing = stage_gaps(sweep_dir, specs)
        if missing:
            stream.write(f"decide {plan.name}: stage {stage} has {len(missing)} cells without a row "
                         f"({result.failed} failed); run the same command again to retry them before the test "
                         f"looks\n")
            return DecideResult(plan.name, sweep_dir, looks, False, False)
        if lost:
            stream.write(f"decide {plan.name}: lost so far (no base met its bar; counted in their stage, in no "
                         f"comparison): trial{'s' * (len(lost) > 1)} {', '.join(map(str, lost))}\n")
        test = judge(plan, store.read_rows(sweep_dir), stage)
        now = [_look_record(plan, i + 1, look, looks[i]["trained"] if i < len(looks) else
                            [t for t in reg.treatments if t in needed])
               for i, look in enumerate(test.looks)]
        for old, new in zip(looks, now):
            if not _same(old, new):
                raise SweepError(f"sweep {plan.name}: the rows of stages 1-{old['stage']} changed since the test looked "
                                 f"at them (decide.json, stage {old['stage']}); a look is not redrawn: restore the "
                                 f"rows or start another --name")
        if len(now) <= len(looks):  # the test had already stopped: nothing new to record
            break
        looks = looks + [{**now[len(looks)], "lost_trials": lost}]
        last = looks[-1]
        finished = is_finished(plan, looks)
        _write(sweep_dir, plan, looks, finished)
        stream.write(f"decide {plan.name}: look {stage} ({last['trials']} trials): " + "; ".join(
            f"{c}: {d} (|T| {abs(last['statistic'][c]):.4g}, boundary {_fmt(last['boundary'][c])})"
            if d == CONTINUE else describe(d, c) for c, d in last["decision"].items()) + "\n")
    if finished and looks:
        last = looks[-1]
        left = len(plan.trials) - last["trials"]
        saved = f"; the grid's other {left} trials were not started" if left else ""
        decided = all(d in (LARGER, SMALLER) for d in last["decision"].values())
        how = "decided after" if decided else "ended at the most it may use,"
        stream.write(f"decide {plan.name}: {how} {last['trials']} of {len(plan.trials)} trials: "
                     + "; ".join(describe(d, c) for c, d in last["decision"].items()) + saved + "\n")
    return DecideResult(plan.name, sweep_dir, looks, finished, True)
