"""The sweep service end to end on real Ray: smoke sweep (and stats / query of it by name), the smoke sweep
damaged, extended and its driver SIGKILLed then resumed, workers killed mid-cell, a cell that fails deterministically.
(A two-node Ray cluster on loopback: tests/test_s3.py, with results on S3.)

Every sweep runs as a CLI subprocess (as a user would), so a killed driver cannot take pytest
with it; processes started here run in their own sessions and are killed in teardown. Workers
are killed from the test, as an OOM killer or a lost node would: no hook in the code under test.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pyarrow.parquet as pq
import pytest
import sockets
from harness import (
    KILL_GRID,
    assert_rows_match,
    cli,
    comparable_rows,
    env,
    expected_rows,
    hold_a_running_cell_at_its_checkpoint,
    kill_all,
    kill_group,
    newest_state,
    parquet_files,
    process_environ,
    process_name,
    python_program,
    ray_workers_running,
    read_log,
    session_processes,
    space,
    start_cli,
    wait_for,
    wait_until_gone,
)
from planted import raw_pickle

from asp_dist.cli import main
from asp_dist.results import store
from asp_dist.sweep import ledger
from asp_dist.sweep.base_cache import rejected_path
from asp_dist.sweep.spaces import expand, space_file
from asp_dist.training.row import schema as row_schema

pytestmark = pytest.mark.slow


# A Ray worker process is "ray::IDLE" until it runs an actor, then the actor's class (/proc/PID/comm: 15 bytes)
RAY_WORKER_NAMES = ("ray::IDLE", "ray::ImplicitFu", "ray::Hub")
SMOKE_DRIVER_TOKEN = "asp-dist-smoke-driver"  # in the smoke driver's environment; Tune hands it to trainables


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """`asp-dist sweep smoke --logger tensorboard --logger json` (18 tiny signaling cells), run once for the tests
    that read it. While it runs, the listening TCP sockets of its whole process tree, the names of its Ray
    worker processes (test_sweep_listens_on_loopback_only), the Python programs of the tree and the trainable
    workers' environments (test_ray_workers_start_lean) are sampled. The driver has a variable that Tune hands
    its trainables (AWS_SECURITY_TOKEN, unused on local disk)."""
    results = tmp_path_factory.mktemp("smoke-results")
    logs = tmp_path_factory.mktemp("smoke-logs")
    with open(logs / "out", "w+") as out, open(logs / "err", "w+") as err:  # files: a full pipe cannot stall it
        proc = subprocess.Popen([sys.executable, "-m", "asp_dist.cli", "sweep", "smoke", "--results", str(results),
                                 "--logger", "tensorboard", "--logger", "json"],
                                env=env(AWS_SECURITY_TOKEN=SMOKE_DRIVER_TOKEN), stdout=out, stderr=err, text=True,
                                start_new_session=True)
        seen: dict[tuple[str, int], str] = {}  # (address, port) -> name of the process listening on it
        ray_workers: dict[int, Counter] = {}  # pid -> how many samples saw the sweep's Ray worker under each name
        programs: dict[int, set[str]] = {}  # pid -> the Python scripts it was seen running (exec keeps the pid)
        trainable_env: dict[int, dict[str, str]] = {}  # a trainable worker's pid -> its environment
        token_file = Path.home() / ".ray" / "auth_token"
        had_token_file = token_file.exists()
        deadline = time.monotonic() + 420
        try:
            while proc.poll() is None and time.monotonic() < deadline:
                tree = sockets.process_tree(proc.pid)
                for pid, address, port in sockets.listening(tree):
                    seen.setdefault((address, port), process_name(pid))
                for pid in tree:
                    if (name := process_name(pid)).startswith(RAY_WORKER_NAMES):
                        ray_workers.setdefault(pid, Counter())[name] += 1
                    if program := python_program(pid):
                        programs.setdefault(pid, set()).add(program)
                    if name == "ray::ImplicitFu" and pid not in trainable_env:
                        trainable_env[pid] = process_environ(pid)
                time.sleep(0.2)
            proc.wait(timeout=max(1, deadline - time.monotonic()))
        finally:
            kill_group(proc)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, (logs / "out").read_text(), (logs / "err").read_text())
    return results, done, SimpleNamespace(listening=seen, ray_workers=ray_workers, programs=programs,
                                          trainable_env=trainable_env,
                                          wrote_token_file=token_file.exists() and not had_token_file)


@pytest.mark.xdist_group("smoke")  # shares a module fixture: one worker
def test_sweep_listens_on_loopback_only(smoke):
    """Nothing the embedded Ray or the driver starts accepts connections from beyond 127.0.0.1 (why: an open
    Ray head on a shared network runs anyone's code): GCS, raylet, workers and the driver all bind loopback."""
    _, proc, seen = smoke
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = set(seen.listening.values())
    assert {"gcs_server", "raylet"} <= names and any(n.startswith("ray::") for n in names), seen.listening
    assert [f"{name} on {address}:{port}" for (address, port), name in seen.listening.items()
            if not sockets.is_loopback(address)] == []
    assert not seen.wrote_token_file, "the sweep wrote a Ray token file into the home directory"
    # Ray starts no worker that no cell can use (ray_host.SYSTEM_CONFIG). Before, one pool worker idled the whole
    # sweep. Counted as a worker only ever seen idle, in a second's samples or more: one started for an actor is
    # idle for a moment, and under load Tune now and then starts a third trainable actor (seen in .ci/run).
    idle_all_along = {pid: names for pid, names in seen.ray_workers.items()
                      if set(names) == {"ray::IDLE"} and names["ray::IDLE"] >= 5}
    assert not idle_all_along and any(names["ray::Hub"] for names in seen.ray_workers.values()), seen.ray_workers


@pytest.mark.xdist_group("smoke")  # shares a module fixture: one worker
def test_ray_workers_start_lean(smoke):
    """The embedded Ray starts no process a sweep does not use (asp_dist/sweep/worker_start.py, ray_host): no
    trainable worker goes through Ray's setup_worker.py (Tune's runtime env, set by inheritance instead), and
    neither the autoscaler monitor nor the log monitor runs. What the runtime env gave the trainables they still
    have: Tune's PL_DISABLE_FORK=1 and the driver's AWS_SECURITY_TOKEN."""
    _, proc, seen = smoke
    assert proc.returncode == 0, proc.stderr[-3000:]
    ran = set().union(*seen.programs.values())
    assert "default_worker.py" in ran, seen.programs  # the sampling sees Ray's Python processes
    assert not ran & {"setup_worker.py", "monitor.py", "log_monitor.py"}, seen.programs
    assert seen.trainable_env and all(
        (e.get("PL_DISABLE_FORK"), e.get("AWS_SECURITY_TOKEN")) == ("1", SMOKE_DRIVER_TOKEN)
        for e in seen.trainable_env.values()), {pid: sorted(e) for pid, e in seen.trainable_env.items()}


@pytest.mark.xdist_group("smoke")  # shares a module fixture: one worker
def test_smoke_sweep_end_to_end(smoke):
    results, proc, _ = smoke
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "18/18 cells done, 0 failed" in proc.stdout
    sweep_dir = results / "smoke"
    files = parquet_files(sweep_dir)
    assert len(files) == 18
    for f in files:
        assert pq.read_schema(f).remove_metadata() == row_schema("signaling")
    df = store.read_rows(sweep_dir)
    assert len(df) == 18 and df["cell_id"].is_unique
    assert set(df["cell_id"]) == {s.cell_id for s in expand("smoke")}
    assert (df["sweep_id"] == "smoke").all() and df["ray_node_id"].notna().all()
    assert df["eval_mixed"].between(0, 1).all()
    assert df.groupby("trial")["base_key"].nunique().eq(1).all()
    assert len(list((sweep_dir / "bases").glob("*.pt"))) == 2, "one base per trial, shared by its 9 cells"
    assert "done" in proc.stderr and "ETA" in proc.stderr  # the counter line
    # What the run ran with (asp_dist.sweep.provenance): the command, the space file, the Ray node.
    first = sweep_dir / "env" / "1"
    assert "sweep smoke" in (first / "command.txt").read_text()
    assert (first / "space.toml").read_text() == space_file("smoke").read_text()
    nodes = json.loads((first / "machine.json").read_text())["ray_nodes"]
    assert len(nodes) == 1 and nodes[0]["address"] == "127.0.0.1" and nodes[0]["cpus"] >= 1
    # A row names the run's node (ray_node_id) and the CPU that trained it (model and torch's vector kernels).
    assert set(df["ray_node_id"]) == {nodes[0]["node_id"]}
    cpu = json.loads((first / "machine.json").read_text())["cpu_model"]
    assert df["cpu_model"].str.startswith(f"{cpu} (").all(), df["cpu_model"].unique()
    assert "torch==" in (first / "distributions.txt").read_text()
    # Running it again retrains nothing, touches no file and records nothing: it trained nothing.
    mtimes = {f: f.stat().st_mtime_ns for f in files}
    env_mtimes = {f: f.stat().st_mtime_ns for f in first.iterdir()}
    again = cli("sweep", "smoke", "--results", str(results))
    assert again.returncode == 0 and "18 already done" in again.stderr
    assert {f: f.stat().st_mtime_ns for f in parquet_files(sweep_dir)} == mtimes
    assert {f: f.stat().st_mtime_ns for f in first.iterdir()} == env_mtimes
    assert "nothing to run" in again.stderr and sorted(p.name for p in (sweep_dir / "env").iterdir()) == ["1"]
    # Resuming it is a no-op that says so: no Ray, no lock taken, nothing recorded.
    resumed = cli("resume", "smoke", "--results", str(results))
    assert resumed.returncode == 0 and "all 18 cells are done; nothing to resume" in resumed.stderr, resumed.stderr
    assert "Ray" not in resumed.stderr and sorted(p.name for p in (sweep_dir / "env").iterdir()) == ["1"]
    status = cli("status", "smoke", "--results", str(results))
    assert status.stdout.splitlines()[-1].split() == ["total", "18", "0", "0"]


@pytest.mark.xdist_group("smoke")  # shares a module fixture: one worker
def test_smoke_sweep_feeds_its_trackers_and_rows_are_unchanged(smoke):
    """One tracker run per cell with its whole curve and final metrics (TensorBoard read back with its own
    reader, JSON lines), and rows bit-identical to those of cells run without any tracker."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from asp_dist.tracking.cells import describe_cells

    results, proc, _ = smoke
    assert proc.returncode == 0, proc.stderr[-3000:]
    sweep_dir = results / "smoke"
    specs = expand("smoke")
    df = assert_rows_match(store.read_rows(sweep_dir), expected_rows(specs))
    cells = describe_cells(specs, "smoke", "?")
    runs = sorted(p.parent for p in (sweep_dir / "trackers" / "tensorboard").rglob("events.out.tfevents.*"))
    assert len(runs) == len(set(runs)) == 18
    curves = store.read_curves(sweep_dir)
    for spec in specs[:6]:  # a trial's worth, read back in full
        row = df.set_index("cell_id").loc[spec.cell_id]
        curve = curves[curves["cell_id"] == spec.cell_id]
        acc = EventAccumulator(str(sweep_dir / "trackers" / "tensorboard" / cells[spec.cell_id].run_path))
        acc.Reload()
        assert [e.step for e in acc.Scalars("loss/total")] == [int(s) for s in curve["step"]]
        assert acc.Scalars("eval/mixed")[-1].value == pytest.approx(row["eval_mixed"], rel=1e-6)  # float32 there
        lines = [json.loads(x) for x in (sweep_dir / "trackers" / "json" /
                                         f"{cells[spec.cell_id].run_path}.jsonl").read_text().splitlines()]
        assert [x["step"] for x in lines[1:-1]] == [int(s) for s in curve["step"]]
        assert lines[-1]["final"]["eval_mixed"] == row["eval_mixed"]
    tracking = json.loads((sweep_dir / "env" / "1" / "tracking.json").read_text())
    assert tracking["loggers"] == ["tensorboard", "json"]


@pytest.mark.xdist_group("smoke")  # shares a module fixture: one worker
def test_ray_tunes_own_readers_give_one_row_per_trial(smoke):
    """Tuner.restore(...).get_results().get_dataframe() and ExperimentAnalysis read Tune's JSON/CSV logs: one
    row per trial with its cell ids and final metrics (the Parquet rows stay the truth)."""
    from ray import tune

    from asp_dist.sweep.trial import train_cell

    results, proc, _ = smoke
    assert proc.returncode == 0, proc.stderr[-3000:]
    experiment = results / "smoke" / "tune" / "run-1"
    grid = store.read_rows(results / "smoke").set_index("cell_id")
    restored = tune.Tuner.restore(str(experiment), trainable=train_cell).get_results()
    assert len(restored) == 18 and not restored.errors
    frame = restored.get_dataframe()
    analysis = tune.ExperimentAnalysis(str(experiment)).dataframe()
    for table in (frame, analysis):
        assert len(table) == 18 and set(table["cell_ids"]) == set(grid.index)
        assert (table.set_index("cell_ids")["eval_mixed"] == grid.loc[table["cell_ids"], "eval_mixed"].values).all()


@pytest.mark.xdist_group("smoke")  # shares a module fixture: one worker
def test_stats_and_query_find_the_sweep_by_name_under_results(smoke, tmp_path, monkeypatch, capsys):
    results, proc, _ = smoke
    assert proc.returncode == 0, proc.stderr[-3000:]
    monkeypatch.chdir(tmp_path)  # no ./results here: the name must be looked up under --results
    assert main(["query", "smoke", "--results", str(results), "--sql",
                 "SELECT method, count(*) AS n FROM cells GROUP BY method ORDER BY method", "--format", "csv"]) == 0
    assert capsys.readouterr().out.split() == ["method,n", "asp,6", "osp,6", "pc,6"]
    assert main(["stats", "smoke", "--results", str(results), "--no-figures", "--bootstrap", "200", "--quiet"]) == 0
    summary = pd.read_parquet(results / "smoke" / "stats" / "summary.parquet")
    assert set(summary["treatment"]) == {"pc", "osp", "asp"} and summary["n"].sum() == 18
    assert "18 rows" in (results / "smoke" / "report.md").read_text()


def sigkill(pid: int) -> bool:
    try:
        os.kill(pid, signal.SIGKILL)
        return True
    except ProcessLookupError:  # it ended on its own meanwhile
        return False


def latest_checkpoint(sweep_dir: Path, cell_id: str) -> int:
    """Index of the newest checkpoint Tune persisted for a cell of the first experiment (-1: none)."""
    found = [int(p.name.rsplit("_", 1)[1]) for p in (sweep_dir / "tune" / "run-1" / cell_id).glob("checkpoint_*")]
    return max(found, default=-1)


def test_killed_worker_is_retried_and_failing_cells_do_not_stop_the_sweep(tmp_path):
    grid = space(tmp_path, """
[fixed]
method = "asp"
unpaired_size = 256

[[grid]]
fixed = { train_steps = 400, trial = 0 }
axes = { paired = [0] }

[[grid]]  # long enough to be killed mid-run (about 1.5 s on one core; checkpoints every 0.2 s)
fixed = { train_steps = 1500, trial = 0 }
axes = { paired = [2, 4] }

[[grid]]  # its own trial, so that its base can be the rejected one
fixed = { train_steps = 400, trial = 1 }
axes = { paired = [8] }
""")
    specs = expand(grid)
    cell = {s.paired: s.cell_id for s in specs}
    sweep_dir = tmp_path / "f"
    # p8 fails deterministically: its trial's base is on record as never meeting its bar (what
    # base_cache writes after the last attempt), so the cell fails at once, without a retry.
    sweep_dir.mkdir()
    store.write_manifest(sweep_dir, ledger.new_manifest("f", "grid", specs))
    rejected = rejected_path(store.bases_dir(sweep_dir), next(s.base_key for s in specs if s.paired == 8))
    rejected.parent.mkdir()
    rejected.write_text(json.dumps({"error": "no base met the bar (planted by the test)"}))

    ray_temp = f"/tmp/asp-kw-{os.getpid()}"
    out_file, err_file = tmp_path / "out.txt", tmp_path / "err.txt"
    with open(out_file, "w") as out_fh, open(err_file, "w") as err_fh:  # files: a full pipe would block the driver
        driver = subprocess.Popen([sys.executable, "-m", "asp_dist.cli", "sweep", grid, "--name", "f", "--results",
                                   str(tmp_path), "--max-failures", "1", "--checkpoint-every", "0.2",
                                   "--ray-temp-dir", ray_temp], env=env(), start_new_session=True, stdout=out_fh,
                                  stderr=err_fh)
    killed_p2, killed_p4 = [], set()
    try:
        deadline = time.monotonic() + 420
        while driver.poll() is None and time.monotonic() < deadline:
            # p2: killed once, mid-run, after Tune holds a checkpoint of it (the second one is
            # written only after the first was reported, so the first is complete).
            if not killed_p2 and latest_checkpoint(sweep_dir, cell[2]) >= 1 and not store.is_done(
                    sweep_dir, "signaling", "asp", cell[2]):
                killed_p2 += [pid for pid in ray_workers_running(cell[2], ray_temp) if sigkill(pid)]
            # p4: every worker that runs it is killed, until Tune gives up on the cell.
            if cell[4] not in store.failed_cells(sweep_dir):
                killed_p4 |= {pid for pid in set(ray_workers_running(cell[4], ray_temp)) - killed_p4 if sigkill(pid)}
            time.sleep(0.05)
        driver.wait(60)
    finally:
        kill_group(driver)
        shutil.rmtree(ray_temp, ignore_errors=True)
    out, err = out_file.read_text(), err_file.read_text()
    assert driver.returncode == 1, err[-3000:]
    assert "2/4 cells done, 2 failed" in out
    assert killed_p2, "the worker of the p2 cell was not killed"
    # Every process seen in p4's directory was killed: at least the first attempt and the max_failures=1
    # retry. The attempts are counted by the failure record below; with 1500-step cells a third process
    # was sometimes seen there and killed without counting as an attempt (what it was is not known).
    assert len(killed_p4) >= 2, killed_p4
    done = store.read_rows(sweep_dir)
    assert set(done["cell_id"]) == {cell[0], cell[2]}, "the killed worker's cell did not complete"
    resumed = done.set_index("cell_id")["resumed_from_step"]
    assert resumed[cell[2]] > 0, "the retried cell started over instead of continuing from its checkpoint"
    failed = store.failed_cells(sweep_dir)
    assert set(failed) == {cell[4], cell[8]}
    assert "failed after 2 attempt(s)" in failed[cell[4]]["error"]  # worker died twice: 1 retry
    assert "BaseRejected: no base met the bar (planted" in failed[cell[8]]["error"]  # deterministic: no retry
    status = cli("status", "f", "--results", str(tmp_path), "--failed").stdout
    assert status.splitlines()[-3].split() == ["total", "2", "2", "0"] and f"failed {cell[4]}" in status

    # resume retries the failed cells (the faults are gone) and never touches finished ones: the
    # worker-killed cell in the restored Tune experiment, the deterministic one in a fresh one.
    rejected.unlink()
    mtimes = {f: f.stat().st_mtime_ns for f in parquet_files(sweep_dir)}
    second = cli("resume", "f", "--results", str(tmp_path))
    assert second.returncode == 0, second.stderr[-3000:]
    assert all(f.stat().st_mtime_ns == m for f, m in mtimes.items())
    assert not store.failed_cells(sweep_dir)
    assert (sweep_dir / "tune" / "run-2").is_dir()
    assert_rows_match(store.read_rows(sweep_dir), expected_rows(specs))


@pytest.mark.xdist_group("smoke")  # shares a module fixture: one worker
def test_a_damaged_sweep_extended_then_killed_resumes_to_every_cell_once(smoke, tmp_path):
    """The finished smoke sweep, four of its cell files damaged (cut short, empty, another cell's, a dangling
    link), is grown by the kill grid with `--extend`, and its driver SIGKILLed mid-extension; `resume` finishes it.

    - damaged files are moved into damaged/ with one warning line each and their cells train again, each row
      written once; every valid file is left as it was (same bytes, same mtime);
    - the extension writes its grid and history into manifest.json before any new cell runs;
    - a SIGKILLed driver leaves no process of its Ray behind (the reaper); `status` says "not running" at once;
    - resume: every cell once, rows as uninterrupted, the cells running at the kill continued from their
      checkpoints, and every new cell's tracker runs (json, TensorBoard) hold each curve step once.
    Runs after the other smoke tests: it changes the sweep. (One sweep for four behaviours: each Ray start-up
    costs the suite 10-20 s.)"""
    results, proc, _ = smoke
    assert proc.returncode == 0, proc.stderr[-3000:]
    sweep_dir = results / "smoke"
    files = parquet_files(sweep_dir)
    rows = comparable_rows(store.read_rows(sweep_dir))
    cut, empty, wrong, dangling = files[:4]
    cut.write_bytes(cut.read_bytes()[:200])
    empty.write_bytes(b"")
    wrong.write_bytes(files[4].read_bytes())  # another cell's row under this cell's name
    dangling.unlink()
    dangling.symlink_to(tmp_path / "nowhere.parquet")
    damaged = {p.stem for p in (cut, empty, wrong, dangling)}
    intact = {f: (f.stat().st_mtime_ns, f.read_bytes()) for f in files[4:]}
    status = cli("status", "smoke", "--results", str(results))
    assert status.stdout.splitlines()[-1].split() == ["total", "14", "0", "4"]

    grown = space(tmp_path, 'include = ["smoke"]\n' + KILL_GRID, "smoke-grown.toml")
    specs = expand(grown)
    new_cells = {s.cell_id for s in expand(space(tmp_path, KILL_GRID))}
    assert len(specs) == 22 and len(new_cells) == 4
    ray_temp = f"/tmp/asp-sk-{os.getpid()}"  # short: Ray's socket paths live under it
    driver = start_cli("sweep", grown, "--name", "smoke", "--extend", "--results", str(results),
                       "--checkpoint-every", "0.3", "--ray-temp-dir", ray_temp, "--logger", "json",
                       "--logger", "tensorboard", log_dir=tmp_path / "log")
    trackers = sweep_dir / "trackers"

    def live_points_of_a_running_cell() -> bool:  # curve points in its tracker before the cell has a row
        done = {f.stem for f in parquet_files(sweep_dir)}
        return any(f.stem.rsplit("-", 1)[-1] not in {d.rsplit("-", 1)[-1][:8] for d in done}
                   and len(f.read_text().splitlines()) > 1 for f in trackers.glob("json/**/*.jsonl"))

    try:
        # Killed once a new cell has its row and another, still running, has live points in its tracker and a
        # checkpoint that Tune's state names; that cell's worker is stopped first (harness).
        wait_for(lambda: new_cells & {f.stem for f in parquet_files(sweep_dir)} and live_points_of_a_running_cell(),
                 300, while_alive=driver, what="a new cell done and a running one with live points")
        hold_a_running_cell_at_its_checkpoint(
            lambda: newest_state(sweep_dir / "tune" / "run-2"),
            lambda cell, i: (sweep_dir / "tune" / "run-2" / cell / f"checkpoint_{i:06d}" / "state.pt").is_file(),
            lambda: {f.stem for f in parquet_files(sweep_dir)}, ray_temp, 300, driver)
        running = session_processes(driver.pid, ray_temp)
        assert any("raylet" in c for c in running.values()), running
        driver.send_signal(signal.SIGKILL)
        driver.wait(30)
        killed = time.monotonic()
        # Before the reaper: the raylet's agents lived on for a minute after the driver, trying to reach the GCS.
        left = wait_until_gone(driver.pid, ray_temp, 10)
        reaper_log = Path(ray_temp, f"reaper-{driver.pid}.log")
        assert not left, (f"left running {time.monotonic() - killed:.0f} s after the driver's SIGKILL: {left}; "
                          f"the reaper's log: {reaper_log.read_text() if reaper_log.exists() else 'none'}")
    finally:
        kill_group(driver)  # Ray processes the killed driver started
        kill_all(driver.pid, ray_temp)
        shutil.rmtree(ray_temp, ignore_errors=True)
    _, killed_err = read_log(tmp_path / "log")
    warnings = [line for line in killed_err.splitlines() if "the cell trains again" in line]
    assert len(warnings) == 4 and all(line.startswith("asp-dist: warning: ") for line in warnings), killed_err[-3000:]
    kept = [p for p in (sweep_dir / store.DAMAGED_DIR).rglob("*.parquet") if p.parent.parent.parent.name == "cells"]
    assert {p.stem for p in kept} == damaged and any(p.is_symlink() for p in kept)
    manifest = json.loads((sweep_dir / "manifest.json").read_text())  # written before any new cell ran
    assert manifest["cells"] == [s.cell_id for s in specs] and [h["cells"] for h in manifest["history"]] == [18, 22]
    done_at_kill = len(parquet_files(sweep_dir))
    assert 14 < done_at_kill < len(specs)
    status = cli("status", "smoke", "--results", str(results))
    assert "not running" in status.stdout and f"total{'':<15}{done_at_kill:>7}" in status.stdout

    # Pickles planted where Tune keeps the killed experiment's state (what Tuner.restore would load): never run
    for experiment in [d for d in (sweep_dir / "tune").glob("run-*") if d.is_dir()]:
        for name in ("tuner.pkl", "basic-variant-state-2099-01-01_00-00-00.json"):
            (experiment / name).write_bytes(raw_pickle(tmp_path / "ran"))
    resumed = cli("resume", "smoke", "--results", str(results), "--checkpoint-every", "0.3")  # the last run's loggers
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert not (tmp_path / "ran").exists(), "resuming the sweep unpickled a file planted in Tune's state"
    assert f"({done_at_kill} already done)" in resumed.stderr and "22/22 cells done, 0 failed" in resumed.stdout
    for path in (cut, empty, wrong, dangling):
        assert path.is_file() and not path.is_symlink()
    df = store.read_rows(sweep_dir, strict=True)
    assert {k: v for k, v in comparable_rows(df).items() if k not in new_cells} == rows, \
        "a redone cell's row differs from its first run's"
    assert_rows_match(df[df["cell_id"].isin(new_cells)], expected_rows([s for s in specs if s.cell_id in new_cells]))
    assert {f: (f.stat().st_mtime_ns, f.read_bytes()) for f in files[4:]} == intact, "a valid cell was rewritten"
    assert not store.damaged_cells(sweep_dir, {s.cell_id: (s.domain, s.method) for s in specs})
    assert not store.failed_cells(sweep_dir)
    # Cells running at the kill continued from their checkpoints instead of starting over.
    assert df["resumed_from_step"].notna().any(), df[["cell_id", "resumed_from_step"]]
    # ... and their tracker runs too: every curve step once, across the killed and the resumed run (named by the
    # grown grid: docs/tracking.md).
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from asp_dist.tracking.cells import describe_cells

    curves = store.read_curves(sweep_dir)
    for cell_id, cell in describe_cells(specs, "smoke", "?").items():
        if cell_id not in new_cells:
            continue
        steps = [int(x) for x in curves.loc[curves["cell_id"] == cell_id, "step"]]
        lines = [json.loads(x) for x in (trackers / "json" / f"{cell.run_path}.jsonl").read_text().splitlines()]
        assert [x["step"] for x in lines if "step" in x] == steps and "final" in lines[-1], cell_id
        acc = EventAccumulator(str(trackers / "tensorboard" / cell.run_path))
        acc.Reload()
        assert [e.step for e in acc.Scalars("loss/total")] == steps, cell_id
    # Nothing left to add: the same extension again trains nothing and adds no history.
    again = cli("sweep", grown, "--name", "smoke", "--results", str(results), "--extend")
    assert again.returncode == 0 and "(22 already done)" in again.stderr, again.stderr[-2000:]
    assert len(json.loads((sweep_dir / "manifest.json").read_text())["history"]) == 2
