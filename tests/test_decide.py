"""asp-dist decide: the registration's checks, the stage loop (with a stand-in for the sweep runner that writes
rows by hand: no Ray), resuming after a stop between or inside stages, and one end-to-end run on real Ray."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from harness import cli, finished_row, space

from asp_dist.errors import SweepError
from asp_dist.results import store
from asp_dist.study.decide_plan import DecidePlan
from asp_dist.study.decide_run import DECIDE_FILE, check_record, read_record, run_decide
from asp_dist.sweep.ledger import SweepResult
from asp_dist.sweep.plan import RunOptions
from asp_dist.sweep.preflight import check_manifest

GRID = """
[[grid]]
fixed = {{ train_steps = 150, unpaired_size = 256 }}
[grid.axes]
domain = ["signaling"]
method = {methods}
paired = [4, 8]
trial = {{ first = 1000, last = {last} }}
"""
DECIDE = """
[decide]
compare = ["osp vs osp@twin", "osp vs osp@broken"]
stage_trials = 8
permutations = 2000
"""
HIGHER = json.dumps({"mixed": "higher"})


def plan_of(tmp_path: Path, decide: str = DECIDE, methods: str = '["osp", "osp@twin", "osp@broken"]',
            last: int = 1023) -> DecidePlan:
    return DecidePlan.from_space(space(tmp_path, GRID.format(methods=methods, last=last) + decide, "d.toml"), "d")


class FakeRunner:
    """Stands in for sweep.tune.run_plan: writes each missing cell's row by hand (osp and its twin score alike
    up to noise, the broken copy far lower), records the specs it was given, and can stop like Ctrl-C after
    `stop_after_rows` rows."""

    def __init__(self, results: Path, stop_after_rows: int | None = None, fail: dict[int, str] | None = None):
        self.results, self.stop_after_rows, self.calls = results, stop_after_rows, []
        self.fail = fail or {}  # trial -> the error each of its cells fails with

    def __call__(self, plan, options, stream):
        self.calls.append([s.cell_id for s in plan.specs])
        sweep_dir = self.results / plan.name
        # the manifest a run writes before its cells (new, or the stage's grown grid)
        store.write_manifest(sweep_dir, check_manifest(sweep_dir, plan.name, plan.specs, plan.space, extend=True))
        done = store.done_cell_ids(sweep_dir)
        written = failed = 0
        for spec in plan.specs:
            if spec.cell_id in done:
                continue
            if spec.trial in self.fail:
                store.record_failure(sweep_dir, spec.cell_id, spec.domain, spec.method, self.fail[spec.trial])
                failed += 1
                continue
            if self.stop_after_rows is not None and written >= self.stop_after_rows:
                self.stop_after_rows = None
                raise KeyboardInterrupt
            rng = np.random.default_rng([spec.trial, spec.paired, len(spec.method)])
            score = 0.1 if spec.method == "osp@broken" else 0.8 + 0.05 * rng.standard_normal()
            store.write_row(sweep_dir, finished_row(spec, eval_mixed=score, metric_directions=HIGHER), "fake")
            written += 1
        return SweepResult(plan.name, sweep_dir, len(plan.specs), len(plan.specs) - failed, failed)


def decide(plan, results: Path, runner, **kw):
    return run_decide(plan, RunOptions(results=results), io.StringIO(), runner=runner, **kw)


def test_a_clear_difference_is_decided_at_the_first_look_and_its_loser_trains_no_later_trial(tmp_path):
    plan, results = plan_of(tmp_path), tmp_path / "results"
    runner = FakeRunner(results)
    result = decide(plan, results, runner)
    looks = result.looks
    assert looks[0]["decision"] == {"osp vs osp@twin": "continue", "osp vs osp@broken": "larger"}
    assert [look["stage"] for look in looks] == [1, 2, 3] and result.finished
    assert looks[-1]["decision"]["osp vs osp@twin"] == "equal"  # two copies of one method: the most it may use
    broken = {s.cell_id for s in plan.specs if s.method == "osp@broken"}
    stage_one = {s.cell_id for s in plan.specs if s.method == "osp@broken" and s.trial <= 1007}
    assert set(runner.calls[-1]) & broken == stage_one  # the decided loser trained stage 1 only
    assert json.loads((results / "d" / DECIDE_FILE).read_text())["looks"] == looks
    again = FakeRunner(results)
    assert decide(plan, results, again).looks == looks and again.calls == []  # finished: nothing runs


def test_stopped_between_or_inside_stages_it_continues_to_the_same_record(tmp_path):
    plan = plan_of(tmp_path)
    whole = decide(plan, tmp_path / "whole", FakeRunner(tmp_path / "whole")).looks
    results = tmp_path / "stopped"
    assert len(decide(plan, results, FakeRunner(results), stop_after=1).looks) == 1  # between stages
    inside = FakeRunner(results, stop_after_rows=5)  # inside stage 2: some of its rows written, no look
    with pytest.raises(KeyboardInterrupt):
        decide(plan, results, inside)
    assert len(read_record(results / "d")["looks"]) == 1
    resumed = FakeRunner(results)
    assert decide(plan, results, resumed).looks == whole
    assert resumed.calls[0] == inside.calls[0]  # the interrupted stage's grid, continued


REJECTED = "Traceback ...\nBaseRejected: signaling base for trial 1003: no attempt of 5 reached the bar"


def test_a_trial_whose_base_met_no_bar_is_lost_and_the_stage_still_looks(tmp_path):
    """A lost trial counts toward its stage and enters no comparison: the looks are those of the same rows with
    the trial's differences zero; any other failure leaves the stage without a look until it is retried."""
    plan, results = plan_of(tmp_path), tmp_path / "results"
    result = decide(plan, results, FakeRunner(results, fail={1003: REJECTED}), stop_after=1)
    assert result.complete and result.looks[0]["lost_trials"] == [1003]
    assert result.looks[0]["trials"] == 8 and result.looks[0]["decision"]["osp vs osp@broken"] == "larger"
    # the statistic is the sum over the other seven trials
    rows = store.read_rows(results / "d")
    per_trial = rows.pivot_table(index="trial", columns="method", values="eval_mixed", aggfunc="mean")
    expected = float((per_trial["osp"] - per_trial["osp@broken"]).sum())
    assert 1003 not in per_trial.index
    assert result.looks[0]["statistic"]["osp vs osp@broken"] == pytest.approx(expected)
    other = tmp_path / "other"
    stopped = decide(plan, other, FakeRunner(other, fail={1003: "Traceback ...\nRuntimeError: worker died"}))
    assert not stopped.complete and stopped.looks == []


def test_rows_changed_under_a_recorded_look_are_refused(tmp_path):
    plan, results = plan_of(tmp_path), tmp_path / "results"
    decide(plan, results, FakeRunner(results), stop_after=1)
    path = next(p for p in store.cell_files(results / "d") if "broken" in str(p))
    spec = next(s for s in plan.specs if s.cell_id in path.name)
    path.unlink()
    store.write_row(results / "d", finished_row(spec, eval_mixed=5.0, metric_directions=HIGHER), "edited")
    with pytest.raises(SweepError, match="changed since the test looked"):
        decide(plan, results, FakeRunner(results))


def test_a_changed_registration_or_grid_is_refused_once_a_stage_has_run(tmp_path):
    plan, results = plan_of(tmp_path), tmp_path / "results"
    decide(plan, results, FakeRunner(results), stop_after=1)
    record = read_record(results / "d")
    assert check_record(plan, record) == record["looks"]
    for other in (plan_of(tmp_path, DECIDE.replace("stage_trials = 8", "stage_trials = 12")),
                  plan_of(tmp_path, last=1031)):
        with pytest.raises(SweepError, match="cannot change once a stage has run"):
            check_record(other, record)


@pytest.mark.parametrize("table, message", [
    ('compare = ["osp vs pc"]', "not a method of the grid"),
    ('compare = ["osp osp@twin"]', 'must read "A vs B"'),
    ('compare = ["osp vs osp"]', 'must read "A vs B"'),
    ('compare = ["osp vs osp@twin", "osp@twin vs osp"]', "twice"),
    ('compare = ["osp vs osp@twin"]', "in no comparison"),
    ('compare = ["osp vs osp@twin", "osp vs osp@broken"]\nalpha = 0.7', "alpha = 0.7 is out of range"),
    ('compare = ["osp vs osp@twin", "osp vs osp@broken"]\ntest = "t-test"', "test must be one of"),
    ('compare = ["osp vs osp@twin", "osp vs osp@broken"]\nstage_trials = 40', "more than the grid's 24 trials"),
    ('compare = ["osp vs osp@twin", "osp vs osp@broken"]\npaired = { first = 16, last = 32 }', "holds none"),
    ('compare = ["osp vs osp@twin", "osp vs osp@broken"]\ntest = "e-value"\nbeta = 0.1', "needs test"),
    ('compare = ["osp vs osp@twin", "osp vs osp@broken"]\nstage_trials = 5', "cannot decide at the first look"),
    ('compare = ["osp vs osp@twin", "osp vs osp@broken"]\nstages = 3', "unknown key(s) stages"),
])
def test_a_bad_registration_is_one_line(tmp_path, table, message):
    with pytest.raises(SweepError, match=message.replace("(", r"\(").replace(")", r"\)")) as e:
        plan_of(tmp_path, "[decide]\n" + table)
    assert "\n" not in str(e.value)


def test_a_decided_verdict_is_on_fresh_trials_and_needs_a_registration(tmp_path):
    with pytest.raises(SweepError, match="fresh ids from 1000"):
        DecidePlan.from_space(space(tmp_path, GRID.format(methods='["osp", "osp@twin", "osp@broken"]', last=1017)
                                    .replace("first = 1000", "first = 900") + DECIDE, "early.toml"))
    with pytest.raises(SweepError, match="has no \\[decide\\] table"):
        DecidePlan.from_space("smoke")


def test_the_stages_partition_the_grid(tmp_path):
    plan = plan_of(tmp_path, last=1020)  # 21 trials in stages of 8: 8, 16, 21
    assert plan.stages == 3 and [len(plan.stage_trials(s)) for s in (1, 2, 3)] == [8, 16, 21]
    assert plan.stage_trials(3) == tuple(range(1000, 1021))
    every = {"osp", "osp@twin", "osp@broken"}
    assert {s.cell_id for s in plan.stage_specs([every] * 3)} == {s.cell_id for s in plan.specs}
    later = {"osp", "osp@twin"}
    specs = plan.stage_specs([every, later, later])  # the broken copy decided at the first look
    assert {s.trial for s in specs if s.method == "osp@broken"} == set(range(1000, 1008))
    assert {s.trial for s in specs if s.method == "osp@twin"} == set(range(1000, 1021))
    assert {s.trial for s in plan.stage_specs([every, later])} == set(range(1000, 1016))


@pytest.mark.slow
def test_decide_smoke_on_ray_stops_each_comparison_as_registered(tmp_path):
    """The shipped smoke registration on real Ray, stopped after its first stage and continued."""
    results = tmp_path / "results"
    first = cli("decide", "decide-smoke", "--results", str(results), "--stages", "1")
    assert first.returncode == 0, first.stderr
    record = read_record(results / "decide-smoke")
    assert [look["decision"] for look in record["looks"]] == [
        {"osp vs osp@twin": "continue", "osp vs osp@broken": "larger"}]
    second = cli("decide", "decide-smoke", "--results", str(results))
    assert second.returncode == 0, second.stderr
    record = read_record(results / "decide-smoke")
    assert record["finished"] and record["looks"][-1]["decision"] == {"osp vs osp@twin": "equal",
                                                                      "osp vs osp@broken": "larger"}
    rows = store.read_rows(results / "decide-smoke")
    assert sorted(rows[rows["method"] == "osp@broken"]["trial"].unique()) == list(range(1000, 1008))
    assert len(rows) == 48 + 32  # stage 2 trained osp and its twin only
    assert "ended at the most it may use, 16 of 16 trials" in second.stderr
    shutil.copy(results / "decide-smoke" / DECIDE_FILE, tmp_path / "before.json")
    third = cli("decide", "decide-smoke", "--results", str(results))  # finished: nothing runs, nothing changes
    assert third.returncode == 0 and "embedded Ray" not in third.stderr
    assert (results / "decide-smoke" / DECIDE_FILE).read_text() == (tmp_path / "before.json").read_text()


def test_the_report_of_a_decided_sweep_shows_its_looks_and_verdict(tmp_path):
    from asp_dist.analysis import run_stats
    from asp_dist.analysis.document import render_markdown
    from asp_dist.analysis.report import build_report

    plan, results = plan_of(tmp_path), tmp_path / "results"
    decide(plan, results, FakeRunner(results))
    text = render_markdown(build_report(run_stats([results / "d"]), tmp_path / "out"))
    assert ("osp vs osp@twin: **no difference shown**; osp vs osp@broken: **osp better** — ended at the most it may "
            "use after 24 of 24 trials (1000–1023).") in text
    assert "| 1 | 8 | 1000–1007 | osp vs osp@broken |" in text and "| 3 | 24 | 1000–1023 | osp vs osp@twin |" in text
