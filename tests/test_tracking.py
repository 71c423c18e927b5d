"""Live trackers (asp_dist.tracking) on their real libraries, without Ray: the pipeline's live points, how
cells are grouped, and every registered tracker driven through the hub -- a cell's points logged once per
step, also when a fresh hub (a resumed sweep) resends its restored curve, read back with the tracker's own
reader (TensorBoard's EventAccumulator and a real `tensorboard` server, MlflowClient, W&B's run records).
The sweep-level checks (rows unchanged, Tune's readers, SIGKILL + resume) are in test_sweep.py."""

from __future__ import annotations

import json
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
from harness import free_port, kill_group, wait_for

from asp_dist.cli import main
from asp_dist.spec import CellSpec
from asp_dist.tracking import TRACKERS, TrackingSettings, tracker_class
from asp_dist.tracking.base import metric_name
from asp_dist.tracking.cells import describe_cells
from asp_dist.tracking.hub import Feed, Hub
from asp_dist.training import engines
from asp_dist.training.pipeline import run_unit
from asp_dist.training.row import comparable

SPEC = CellSpec(domain="signaling", method="asp", paired=2, trial=0, train_steps=100, unpaired_size=64).resolved()
METRICS = ("mixed", "convention_match")


def cells_of(*specs, sweep="s"):
    return describe_cells(specs, sweep, "rev0", lambda d: METRICS)


def points(steps):
    """Curve points as the pipeline makes them: a loss every point, a probe every 5th."""
    out = []
    for i, step in enumerate(steps):
        p = {"step": float(step), "lambda_unpaired_now": 1.0, "loss_paired": 1.0 / step, "loss_total": 2.0 / step}
        if i % 5 == 4:
            p["probe_mixed"] = step / 1000
        out.append(p)
    return out


# ---- the pipeline's live points -----------------------------------------------------------------------
def test_points_arrive_while_the_cell_trains_and_rows_do_not_change():
    calls = []
    live = run_unit(engines.lone_trainer(SPEC), [SPEC], curves=True,
                    on_points=lambda batch: calls.append([(s.cell_id, [p["step"] for p in pts]) for s, pts in batch]))
    quiet = run_unit(engines.lone_trainer(SPEC), [SPEC], curves=True)
    assert comparable(live[0].row) == comparable(quiet[0].row)  # rows are the truth, with or without trackers
    assert len(calls) > 10, "points come in many calls while training, not once at the end"
    sent = [step for call in calls for _, steps in call for step in steps]
    assert sent == [p["step"] for p in live[0].curve]  # each point once, in order: the curve the row's cell has
    assert calls[0][0][1][-1] < SPEC.train_steps  # the first call came before the last update


def test_a_restored_unit_resends_its_curve_from_the_first_point():
    saved = []
    run_unit(engines.lone_trainer(SPEC), [SPEC], curves=True, checkpoint=saved.append, checkpoint_every_steps=60)
    calls = []
    resumed = run_unit(engines.lone_trainer(SPEC), [SPEC], curves=True, restore=saved[0],
                       on_points=lambda batch: calls.extend(p["step"] for _, pts in batch for p in pts))
    assert calls == [p["step"] for p in resumed[0].curve] and calls[0] < 60


# ---- naming and grouping --------------------------------------------------------------------------------
def test_cells_are_grouped_by_condition_and_treatment():
    specs = [CellSpec(domain="signaling", method=m, paired=p, trial=0, signaling_skew=skew,
                      lambda_unpaired=lam if m == "asp" else 1.0).resolved()
             for m in ("osp", "asp") for p in (0, 2) for skew in (0.5, 1.0) for lam in (0.5, 1.0)]
    cells = describe_cells(specs, "grid", "rev", lambda d: ("mixed",))
    asp = next(c for c in cells.values() if c.method == "asp" and c.config["lambda_unpaired"] == 0.5)
    assert asp.condition == "signaling_skew=0.5" or asp.condition == "signaling_skew=1"
    assert asp.treatment == "asp[lambda_unpaired=0.5]"
    assert asp.group == f"signaling/{asp.condition}"
    assert asp.run_path.startswith(f"signaling/{asp.condition}/asp[lambda_unpaired=0.5]/paired=")
    assert len({c.run_path for c in cells.values()}) == len({s.cell_id for s in specs})  # one run per cell
    osp = next(c for c in cells.values() if c.method == "osp")
    assert osp.treatment == "osp" and osp.tags["sweep"] == "grid" and osp.tags["code_revision"] == "rev"


# ---- every tracker, read back with its own tools ---------------------------------------------------------
def read_back(kind: str, settings: TrackingSettings, cell) -> dict:
    """What the tracker holds for the cell: {"steps": {tag: [steps]}, "final": {tag: value}, "state": ...}."""
    root = Path(settings.dir)
    if kind == "tensorboard":
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        acc = EventAccumulator(str(root / "tensorboard" / cell.run_path), size_guidance={"scalars": 0, "tensors": 0})
        acc.Reload()
        steps = {t: [e.step for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}
        final = {t: acc.Scalars(t)[-1].value for t in steps if t.startswith("eval/")}
        return {"steps": steps, "final": final, "hparams": "_hparams_/session_start_info" in acc.summary_metadata}
    if kind == "mlflow":
        from mlflow.tracking import MlflowClient

        client = MlflowClient(settings.mlflow_uri)
        experiment = client.get_experiment_by_name(cell.sweep)
        runs = client.search_runs([experiment.experiment_id], f"tags.`asp_dist.cell_id` = '{cell.cell_id}'")
        parents = client.search_runs([experiment.experiment_id], "tags.`asp_dist.role` = 'sweep'")
        assert len(runs) == 1 and len(parents) == 1
        run = runs[0]
        assert run.data.tags["mlflow.parentRunId"] == parents[0].info.run_id  # nested under the sweep's run
        assert run.data.params["method"] == cell.method and run.data.tags["asp_dist.trial"] == str(cell.trial)
        steps = {k: [m.step for m in client.get_metric_history(run.info.run_id, k)] for k in run.data.metrics}
        final = {k: v for k, v in run.data.metrics.items() if k.startswith("eval/")}
        return {"steps": steps, "final": final, "status": run.info.status}
    if kind == "wandb":
        from asp_dist.tracking.wandb import records, run_files

        files = run_files(root / "wandb", cell)
        steps, final, group = {}, {}, None
        for f in files:
            for r in records(f):
                kind_ = r.WhichOneof("record_type")
                if kind_ == "history":
                    for item in r.history.item:
                        key = item.key or "/".join(item.nested_key)
                        if not key.startswith("_"):
                            steps.setdefault(key, []).append(r.history.step.num)
                elif kind_ == "summary":
                    for item in r.summary.update:
                        key = item.key or "/".join(item.nested_key)
                        if key.startswith("eval/"):
                            final[key] = json.loads(item.value_json)
                elif kind_ == "run":
                    group = (r.run.run_group, r.run.job_type, r.run.display_name)
        return {"steps": steps, "final": final, "group": group, "files": len(files)}
    if kind == "json":
        lines = [json.loads(x) for x in (root / "json" / f"{cell.run_path}.jsonl").read_text().splitlines()]
        steps = {}
        for line in lines:
            for k in line:
                if "step" in line and k != "step":
                    steps.setdefault(metric_name(k), []).append(line["step"])
        final = {metric_name(k): v for line in lines if "final" in line for k, v in line["final"].items()}
        return {"steps": steps, "final": final, "header": lines[0]["cell"]["cell_id"]}
    raise AssertionError(f"no reader for tracker {kind}: add one to read_back")


@pytest.fixture
def no_wandb_network(monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")


def test_a_w_and_b_run_file_cut_short_reads_as_its_whole_records(tmp_path, no_wandb_network):
    """A killed process leaves its W&B run file with a torn last record; a resumed cell reads the file to find its
    last step. Cut at every 97th byte, the file reads as the full file's records up to the cut (its steps a
    prefix of the full run's), and the tracker resumes after the last whole step, instead of failing and being
    switched off. A record that does not parse before the end is still an error."""
    pytest.importorskip("wandb")
    from asp_dist.tracking.wandb import WandbTracker, history_steps, records, run_files

    settings = TrackingSettings(("wandb",)).resolved(tmp_path)
    (cell,) = cells_of(SPEC).values()
    hub = Hub(settings, "s", {cell.cell_id: cell})
    hub.points([(cell.cell_id, points(range(2, 61, 2)))])
    assert hub.close(interrupted=True) == []
    wait_for(lambda: wandb_runs_ended(settings, cell) == [True], 30, what="the W&B run file ended")
    (path,) = run_files(Path(settings.dir) / "wandb", cell)
    data, full = path.read_bytes(), [r.SerializeToString() for r in records(path)]
    full_steps = history_steps(path)
    assert full_steps == list(range(2, 61, 2))
    cut = tmp_path / "cut.wandb"
    for size in range(8, len(data), 97):
        cut.write_bytes(data[:size])
        got = [r.SerializeToString() for r in records(cut)]
        assert got == full[:len(got)], size
        assert history_steps(cut) == full_steps[:len(history_steps(cut))], size
    path.write_bytes(data[:len(data) // 2])  # the run file as a killed process left it
    tracker = WandbTracker(settings, "s")
    try:
        assert tracker.open_cell(cell) == history_steps(path)[-1] < 60
    finally:
        tracker.close(interrupted=True)
    damaged = bytearray(data)
    damaged[14] = 0  # the first record's first byte (after 7 of file and 7 of record header): field number 0
    cut.write_bytes(bytes(damaged))
    from google.protobuf.message import DecodeError

    with pytest.raises(DecodeError):  # loud, not read as a shorter run
        list(records(cut))


def wandb_runs_ended(settings, cell) -> list[bool]:
    """For each W&B run file of the cell, in start order: whether it ends with the run's exit record."""
    from asp_dist.tracking.wandb import records, run_files

    ended = []
    for f in run_files(Path(settings.dir) / "wandb", cell):
        try:
            kinds = [r.WhichOneof("record_type") for r in records(f)]
        except (OSError, ValueError):  # not written far enough yet to read
            kinds = []
        ended.append(bool(kinds) and kinds[-1] == "exit")
    return ended


@pytest.mark.parametrize("kind", sorted(TRACKERS))
def test_a_resumed_cell_continues_its_run_with_each_step_once(kind, tmp_path, no_wandb_network):
    settings = TrackingSettings((kind,)).resolved(tmp_path)
    tracker_class(kind).check(settings)
    (cell,) = cells_of(SPEC).values()
    steps = list(range(2, 101, 2))
    first = Hub(settings, "s", {cell.cell_id: cell})
    first.points([(cell.cell_id, points(steps[:10]))])
    first.points([(cell.cell_id, points(steps[:12]))])  # a retried worker resends: nothing twice
    assert first.close(interrupted=True) == []  # the sweep stopped: the cell's run ends as stopped
    if kind == "mlflow":
        assert read_back(kind, settings, cell)["status"] == "KILLED"

    if kind == "wandb":  # W&B names a run's directory by its id and start second: a real resume is seconds later
        opened = int(time.time())
        wait_for(lambda: int(time.time()) > opened, 2, what="the next second")
    second = Hub(settings, "s", {cell.cell_id: cell})  # a resume: a fresh hub, the curve resent from its start
    second.points([(cell.cell_id, points(steps[:30]))])
    second.points([(cell.cell_id, points(steps[30:]))])
    second.finish(cell.cell_id, {"eval_mixed": 0.75, "eval_convention_match": 0.5}, 100)
    assert second.close(interrupted=False) == []

    if kind == "wandb":  # W&B's service may still be writing the run file after finish() returns: wait for its end
        wait_for(lambda: wandb_runs_ended(settings, cell) == [True, True], 30, what="both W&B run files ended")
    got = read_back(kind, settings, cell)
    assert got["steps"]["loss/paired"] == steps, ("every step once, in order, across the two runs", got)
    assert got["steps"]["probe/mixed"] == steps[4::5]
    assert got["final"] == {"eval/mixed": 0.75, "eval/convention_match": 0.5}
    if kind == "tensorboard":
        assert got["hparams"]
    if kind == "mlflow":
        assert got["status"] == "FINISHED"
    if kind == "wandb":
        assert got["group"] == (cell.group, cell.treatment, cell.run_name) and got["files"] == 2
    if kind == "json":
        assert got["header"] == cell.cell_id


@pytest.mark.parametrize("kind", sorted(TRACKERS))
def test_a_failed_cell_ends_its_run_as_failed(kind, tmp_path, no_wandb_network):
    settings = TrackingSettings((kind,)).resolved(tmp_path)
    (cell,) = cells_of(SPEC).values()
    hub = Hub(settings, "s", {cell.cell_id: cell})
    hub.finish(cell.cell_id, {}, 0, "BaseRejected: base never met its bar")
    assert hub.close(False) == []
    if kind == "mlflow":
        assert read_back(kind, settings, cell)["status"] == "FAILED"
    if kind == "json":
        last = (Path(settings.dir) / "json" / f"{cell.run_path}.jsonl").read_text().splitlines()[-1]
        assert json.loads(last)["error"].startswith("BaseRejected")


def test_a_tracker_that_fails_warns_once_and_the_others_go_on(tmp_path, monkeypatch):
    settings = TrackingSettings(("json", "tensorboard")).resolved(tmp_path)
    cells = cells_of(SPEC)
    (cell,) = cells.values()
    hub = Hub(settings, "s", cells)

    def broken(self, cell, pts):
        raise OSError("disk of the event files went away")

    monkeypatch.setattr(tracker_class("tensorboard"), "log", broken)
    hub.points([(cell.cell_id, points([2, 4]))])
    hub.points([(cell.cell_id, points([6, 8]))])
    hub.finish(cell.cell_id, {"eval_mixed": 1.0}, 100)
    warnings = hub.close(False)
    assert len(warnings) == 1 and "logger tensorboard failed while logging" in warnings[0]
    assert "rows are unaffected" in warnings[0]
    assert read_back("json", settings, cell)["steps"]["loss/paired"] == [2, 4, 6, 8]


def test_the_feed_sends_in_batches_and_only_its_cells():
    sent = []

    class FakeHub:  # an actor handle's shape: .points.remote(...), .finish.remote(...)
        class points:
            remote = staticmethod(lambda batch: sent.append(("points", batch)))

        class finish:
            remote = staticmethod(lambda *a: sent.append(("finish", a)))

    other = SPEC.replace(trial=1).resolved()
    feed = Feed(FakeHub(), every_s=3600, only={SPEC.cell_id})
    feed([(SPEC, points([2])), (other, points([2]))])
    feed([(SPEC, points([4]))])
    assert sent == []  # buffered until the interval or the cell's end
    feed.finish(SPEC.cell_id, {"eval_mixed": 1.0}, 100)
    assert [k for k, _ in sent] == ["points", "finish"]
    (batch,) = [b for k, b in sent if k == "points"]
    assert [(cid, [p["step"] for p in pts]) for cid, pts in batch] == [(SPEC.cell_id, [2.0, 4.0])]


@pytest.mark.parametrize("answers", [True, False])
def test_a_cells_end_waits_for_the_hub_and_a_silent_hub_is_given_up_on(answers, capsys):
    """Feed.finish returns once the hub has taken the cell's end (its caller writes the row only then), waiting
    on that call's answer; a hub that does not answer within finish_wait_s gets one warning and is not waited
    for longer."""
    calls = []

    class FakeHub:
        class points:
            remote = staticmethod(lambda batch: calls.append("points") or "points-ref")

        class finish:
            remote = staticmethod(lambda *a: calls.append("finish") or "finish-ref")

    def wait(ref, seconds):
        calls.append(("wait", ref, seconds))
        return answers

    feed = Feed(FakeHub(), every_s=3600, wait=wait, finish_wait_s=7)
    feed([(SPEC, points([2]))])
    assert feed.finish(SPEC.cell_id, {}, 100) is answers
    assert calls == ["points", "finish", ("wait", "finish-ref", 7)]
    err = capsys.readouterr().err
    assert (err == "") is answers
    if not answers:
        assert err.startswith("asp-dist: warning: the tracker hub did not take cell ") and "within 7 s" in err
    # The next cell's end: waited for again only if the hub answered the last one.
    feed.finish("another-cell", {}, 100)
    assert calls[3:] == ["finish", ("wait", "finish-ref", 7)] if answers else calls[3:] == ["finish"]
    assert capsys.readouterr().err == ""


def test_a_worker_waits_on_the_hubs_answer_and_stops_waiting_for_a_silent_hub(monkeypatch):
    """In a sweep the feed waits with ray.wait and reads the answer: an answer is taken, no answer in time or
    an actor error (the hub died with its driver) is not; a hub that left one end unanswered is not waited for
    again by that worker process."""
    import ray

    from asp_dist.sweep import trial

    ready, errors = [], []

    def fake_wait(refs, timeout):
        assert timeout == 7
        return (refs, []) if ready else ([], refs)

    def fake_get(ref):
        if errors:
            raise ray.exceptions.RayActorError()
        return None

    monkeypatch.setattr(trial.ray, "wait", fake_wait)
    monkeypatch.setattr(trial.ray, "get", fake_get)
    assert trial._answered("ref", 7) is False  # no answer in time
    ready.append(1)
    assert trial._answered("ref", 7) is True
    errors.append(1)
    assert trial._answered("ref", 7) is False  # the hub is gone

    class Hub:
        class points:
            remote = staticmethod(lambda batch: None)

        class finish:
            remote = staticmethod(lambda *a: "ref")

    monkeypatch.setattr(trial.ray, "is_initialized", lambda: True)
    monkeypatch.setitem(trial._HUBS, "s", Hub())
    monkeypatch.setattr(trial, "_SILENT_HUBS", set())
    feed = trial._feed("s", {SPEC.cell_id})
    assert feed.wait is trial._answered
    monkeypatch.setattr(feed, "wait", lambda ref, seconds: False)
    trial._finish(feed, "s", SPEC.cell_id, {}, 100)
    assert trial._feed("s", {SPEC.cell_id}).wait is None


# ---- a real TensorBoard serves the cells' scalars ---------------------------------------------------------
@pytest.mark.slow
def test_tensorboard_serves_every_cell_on_loopback(tmp_path):
    settings = TrackingSettings(("tensorboard",)).resolved(tmp_path)
    specs = [SPEC, SPEC.replace(method="osp").resolved()]
    cells = cells_of(*specs)
    hub = Hub(settings, "s", cells)
    for cell_id in cells:
        hub.points([(cell_id, points(range(2, 21, 2)))])
        hub.finish(cell_id, {"eval_mixed": 0.5}, 100)
    hub.close(False)
    port = free_port()
    exe = str(Path(sys.executable).with_name("tensorboard"))
    proc = subprocess.Popen([exe, "--logdir", str(tmp_path / "tensorboard"), "--host", "127.0.0.1", "--port",
                             str(port), "--load_fast", "false"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    base = f"http://127.0.0.1:{port}"

    def get(path):
        with urllib.request.urlopen(base + path, timeout=5) as r:
            return json.loads(r.read())

    def tags_served():
        try:
            return len(get("/data/plugin/scalars/tags")) == 2
        except OSError:
            return False

    try:
        wait_for(tags_served, 120, while_alive=proc, what="tensorboard serving both runs")
        tags = get("/data/plugin/scalars/tags")
        assert set(tags) == {c.run_path for c in cells.values()}
        run = next(iter(tags))
        assert {"loss/paired", "probe/mixed", "eval/mixed", "schedule/lambda_unpaired"} <= set(tags[run])
        q = urllib.parse.urlencode({"run": run, "tag": "loss/paired"})
        assert [step for _, step, _ in get(f"/data/plugin/scalars/scalars?{q}")] == list(range(2, 21, 2))
    finally:
        kill_group(proc)


# ---- a logger that cannot start is one line, before anything runs ----------------------------------------
@pytest.mark.parametrize("flags, says", [
    (["--logger", "neptune"], "unknown logger 'neptune'"),
    (["--logger", "json", "--logger", "json"], "--logger json is given twice"),
    (["--logger", "mlflow", "--mlflow-uri", "bogus://nowhere"], "--logger mlflow: tracking URI bogus://nowhere"),
    (["--logger", "tensorboard", "--logger-dir", "{tmp}/a-file/trackers"], "--logger tensorboard: cannot write to"),
])
def test_a_logger_that_cannot_start_is_refused_in_one_line(flags, says, tmp_path, capsys):
    results = tmp_path / "results"
    (tmp_path / "a-file").write_text("")  # a directory under a file cannot be made (root may write anywhere else)
    flags = [f.format(tmp=tmp_path) for f in flags]
    assert main(["sweep", "smoke", "--results", str(results), *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("asp-dist: error: ") and says in err[0], err
    assert not results.exists(), "nothing written"


def test_a_missing_tracker_library_says_what_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(tracker_class("wandb"), "module", "wandb_that_is_not_installed")
    assert main(["sweep", "smoke", "--results", str(tmp_path / "r"), "--logger", "wandb"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("asp-dist: error: --logger wandb needs wandb_that_is_not_installed")
    assert "pip install wandb" in err


def test_a_space_files_logging_table_is_checked(tmp_path, capsys):
    space = tmp_path / "g.toml"
    space.write_text('[logging]\nloggers = ["json"]\ncolour = "red"\n[[grid]]\naxes = { domain = ["signaling"], '
                     'method = ["pc"], paired = [0], trial = [0] }\n')
    assert main(["sweep", str(space), "--results", str(tmp_path / "r")]) == 2
    assert "unknown key(s) colour in [logging]" in capsys.readouterr().err
