"""A sweep's life from start to stop leaves nothing behind: a cluster that does not answer is refused
within --connect-timeout with nothing written; the embedded Ray starts no dashboard unless asked and
prunes its old session dirs; checkpoints are staged inside the sweep; a deterministic data error is
recorded once; SIGTERM stops a sweep like Ctrl-C and `resume` finishes it; after a SIGKILL of the
driver no process of its Ray survives.

The first tests need no running Ray (stand-ins for ray.init and tune.report); the last ones run the
CLI in subprocesses, each with its own --ray-temp-dir and in its own session, so that everything it
started can be found (and is killed in teardown) without touching any other Ray on the machine.
"""

from __future__ import annotations

import io
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
from harness import (
    env,
    fingerprint,
    free_port,
    kill_all,
    parquet_files,
    process_name,
    session_processes,
    wait_for,
    wait_until_gone,
)
from planted import PLANTS

from asp_dist import cli
from asp_dist.commands import sweep as sweep_command
from asp_dist.data.mnist import MNISTError
from asp_dist.results import store
from asp_dist.sweep import ledger, preflight, signals
from asp_dist.sweep.spaces import expand

# ---- a cluster that does not answer -------------------------------------------------------------------------
REFUSED_WITHOUT_RAY = """import sys, time
from asp_dist.cli import main
start = time.monotonic()
code = main(sys.argv[1:])
print(code, round(time.monotonic() - start, 2))
assert 'ray' not in sys.modules, 'ray was imported'
"""


@pytest.mark.parametrize("where", ["loopback-port-nothing-listens-on", "unresolvable-host"])
def test_a_cluster_that_does_not_answer_is_refused_in_time_and_nothing_is_written(tmp_path, where):
    address = f"127.0.0.1:{free_port()}" if where.startswith("loopback") else "no-such-host.invalid:6379"
    results = tmp_path / "results"
    proc = subprocess.run([sys.executable, "-c", REFUSED_WITHOUT_RAY, "sweep", "smoke", "--results", str(results),
                           "--address", address, "--connect-timeout", "2"],
                          env=env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    code, seconds = proc.stdout.split()
    assert code == "2" and float(seconds) < 10, proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("asp-dist: error: cannot reach the Ray cluster at ") \
        and address in lines[0], proc.stderr
    assert not results.exists(), "the results tree was written"

    # resume of an existing sweep: refused the same way, its directory untouched.
    sweep_dir = results / "exp"
    sweep_dir.mkdir(parents=True)
    store.write_manifest(sweep_dir, ledger.new_manifest("exp", "smoke", expand("smoke")))
    before = fingerprint(results)
    proc = subprocess.run([sys.executable, "-c", REFUSED_WITHOUT_RAY, "resume", "exp", "--results", str(results),
                           "--address", address, "--connect-timeout", "2"],
                          env=env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.split()[0] == "2", proc.stderr[-2000:]
    assert address in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert fingerprint(results) == before


def test_address_and_connect_timeout_flags(tmp_path, capsys):
    results = ["--results", str(tmp_path / "r")]
    for argv, needle in ((["--address", "localhost"], "write HOST:PORT"),
                         (["--address", "h:99999"], "write HOST:PORT"),
                         (["--connect-timeout", "0"], "--connect-timeout must be > 0"),
                         (["--connect-timeout", "nan"], "--connect-timeout must be > 0"),
                         (["--address", "127.0.0.1:6379", "--dashboard"], "--dashboard starts the embedded")):
        try:
            code = cli.main(["sweep", "smoke", *results, *argv])
        except SystemExit as e:  # a bound of the flag's type: argparse's exit 2
            code = e.code
        assert code == 2
        err = capsys.readouterr().err
        assert needle in err and len(err.strip().splitlines()) == 1, err
    assert preflight.parse_address("ray://head.example:10001") == ("head.example", 10001)
    assert preflight.parse_address("[::1]:6379") == ("::1", 6379)
    assert preflight.parse_address("auto") is None
    assert not (tmp_path / "r").exists()


def test_dashboard_needs_its_packages(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sweep_command, "DASHBOARD_MODULES", ("surely_not_installed_asp_module",))
    assert cli.main(["sweep", "smoke", "--results", str(tmp_path / "r"), "--dashboard"]) == 2
    assert "--dashboard needs Ray's dashboard packages (surely_not_installed_asp_module" in capsys.readouterr().err


@pytest.mark.slow
def test_a_head_that_accepts_but_never_answers_is_given_up_on_in_time(tmp_path):
    """A TCP port that accepts connections but is no Ray head: ray.init would wait for minutes."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(64)
    server.settimeout(0.5)
    address = f"127.0.0.1:{server.getsockname()[1]}"
    accepted, stop = [], threading.Event()

    def accept():
        while not stop.is_set():
            try:
                accepted.append(server.accept()[0])
            except OSError:
                pass

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:  # (before: ray.init waited for minutes; the subprocess's timeout is the guard against that)
        proc = subprocess.run([sys.executable, "-m", "asp_dist.cli", "sweep", "smoke", "--results",
                               str(tmp_path / "results"), "--address", address, "--connect-timeout", "3"],
                              env=env(), capture_output=True, text=True, timeout=120, start_new_session=True)
    finally:
        stop.set()
        thread.join(5)
        for conn in accepted:
            conn.close()
        server.close()
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert f"asp-dist: error: no answer from the Ray cluster at {address} within 3 s" in proc.stderr
    assert not (tmp_path / "results").exists()


# ---- the embedded Ray: dashboard, session dirs ---------------------------------------------------------------
def test_embedded_ray_starts_no_dashboard_unless_asked_and_keeps_the_sweeps_sigterm(monkeypatch, tmp_path):
    from asp_dist.sweep import ray_host

    calls = []

    class Context:
        dashboard_url = "127.0.0.1:8265"

    def fake_init(**kwargs):
        calls.append(kwargs)
        signal.signal(signal.SIGTERM, lambda *a: sys.exit(15))  # what ray.init does
        return Context()

    monkeypatch.setattr(ray_host.ray, "init", fake_init)
    monkeypatch.setattr(ray_host.ray, "shutdown", lambda: None)
    monkeypatch.setattr(ray_host.ray, "is_initialized", lambda: False)
    pruned = []
    monkeypatch.setattr(ray_host, "prune_ray_sessions", lambda d: pruned.append(d) or [])
    monkeypatch.setattr(ray_host, "_start_reaper", lambda d: None)
    out = io.StringIO()
    with signals.sigterm_as_interrupt():
        with ray_host.ray_session(2, None, str(tmp_path), stream=out):
            assert signal.getsignal(signal.SIGTERM) is signals._sigterm, "ray.init's SIGTERM handler was kept"
        with ray_host.ray_session(2, None, str(tmp_path), dashboard=True, stream=out):
            pass
    assert calls[0]["include_dashboard"] is False and calls[0]["dashboard_host"] == "127.0.0.1"
    assert calls[1]["include_dashboard"] is True and calls[1]["dashboard_host"] == "127.0.0.1"
    assert out.getvalue() == "Ray dashboard: http://127.0.0.1:8265\n"
    assert pruned == [str(tmp_path)] * 2
    parser = cli.build_parser()
    for command in (["sweep", "smoke"], ["resume", "x"]):
        assert parser.parse_args(command).dashboard is False
        assert parser.parse_args([*command, "--dashboard"]).dashboard is True


def test_a_sigterm_while_ray_starts_reaches_the_sweep_whatever_handler_ray_installs(monkeypatch, tmp_path):
    """ray.init installs SIGTERM handlers of its own; one that arrives while it runs must still stop the sweep
    once Ray is up (ray_session holds it), not run Ray's handler inside Ray's code, where it was lost. The fake
    init installs a handler that swallows the signal, as the lost case did, then is sent a SIGTERM."""
    from ray._private import utils as ray_utils

    from asp_dist.sweep import ray_host

    started = []

    def fake_init(**kwargs):
        ray_utils.set_sigterm_handler(lambda signum, frame: None)  # what Ray does, in the form that loses it
        os.kill(os.getpid(), signal.SIGTERM)
        started.append(True)
        return type("Context", (), {"dashboard_url": None})()

    monkeypatch.setattr(ray_host.ray, "init", fake_init)
    shut = []
    monkeypatch.setattr(ray_host.ray, "shutdown", lambda: shut.append(True))
    monkeypatch.setattr(ray_host.ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray_host, "prune_ray_sessions", lambda d: [])
    monkeypatch.setattr(ray_host, "_start_reaper", lambda d: None)
    with signals.sigterm_as_interrupt():
        with pytest.raises(KeyboardInterrupt):
            with ray_host.ray_session(2, None, str(tmp_path)):
                pytest.fail("the sweep went on after a SIGTERM during start-up")
        assert signal.getsignal(signal.SIGTERM) is signals._sigterm
    assert started == [True] and shut == [True] and signals.interrupted_by == signal.SIGTERM
    assert ray_utils.set_sigterm_handler is not None and "lambda" not in ray_utils.set_sigterm_handler.__name__


def test_old_ray_sessions_are_pruned_but_never_one_in_use(tmp_path):
    from asp_dist.sweep.ray_host import prune_ray_sessions

    dead = 99_999_999  # above any pid_max: no such process
    names = [f"session_2020-01-0{day}_00-00-00_000000_{dead}" for day in range(1, 10)]
    names[5] = f"session_2020-01-06_00-00-00_000000_{os.getpid()}"  # its driver is alive
    old = time.time() - 3600
    for name in names:
        (tmp_path / name / "logs").mkdir(parents=True)
        (tmp_path / name / "logs" / "raylet.out").write_text("x")
        for p in (tmp_path / name / "logs" / "raylet.out", tmp_path / name / "logs", tmp_path / name):
            os.utime(p, (old, old))
    os.utime(tmp_path / names[3])  # young: a Ray that may be starting
    (tmp_path / "session_latest").symlink_to(tmp_path / names[2])
    (tmp_path / "other").mkdir()
    user = subprocess.Popen(["sleep", "60"], cwd=tmp_path / names[4] / "logs")  # a process works in it
    try:
        removed = prune_ray_sessions(tmp_path, keep=3, min_age_s=300)
    finally:
        user.kill()
        user.wait()
    assert sorted(p.name for p in removed) == names[:2]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names[2:] + ["other", "session_latest"])
    assert prune_ray_sessions(tmp_path / "missing") == []


# ---- the trainable: checkpoints inside the sweep, deterministic data errors --------------------------------
@pytest.fixture
def trainable(monkeypatch, tmp_path):
    """train_cell outside Ray: tune.report records its calls (and what a checkpoint dir holds then). The
    config is a single cell's of older code ("spec", "cell_id"): a restored Tune experiment hands those."""
    from asp_dist.sweep import trial
    from asp_dist.sweep import tune as sweep_tune

    reports = []

    def report(metrics, checkpoint=None):
        seen = None
        if checkpoint is not None:
            seen = (Path(checkpoint.path), sorted(p.name for p in Path(checkpoint.path).iterdir()))
        reports.append((metrics, seen))

    class RuntimeContext:
        def get_node_id(self):
            return "node-0"

    monkeypatch.setattr(sweep_tune.tune, "report", report)
    monkeypatch.setattr(sweep_tune.tune, "get_checkpoint", lambda: None)
    monkeypatch.setattr(trial.ray, "get_runtime_context", RuntimeContext)
    system_tmp = tmp_path / "system-tmp"
    system_tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(system_tmp))
    spec = expand("smoke")[0]
    sweep_dir = tmp_path / "smoke"
    config = {"cell": {"spec": spec.to_dict(), "cell_id": spec.cell_id, "sweep_dir": str(sweep_dir),
                       "sweep_id": "smoke", "checkpoint_every_s": 1e-9}}
    return sweep_tune, config, spec, sweep_dir, system_tmp, reports


def test_checkpoints_are_staged_inside_the_sweep_and_removed_after_the_copy(trainable):
    sweep_tune, config, spec, sweep_dir, system_tmp, reports = trainable
    sweep_tune.train_cell(config)
    saved = [seen for _, seen in reports if seen is not None]
    assert saved, "no checkpoint was reported"
    staging = sweep_dir / sweep_tune.TUNE_DIR / sweep_tune.CKPT_TMP
    for path, files in saved:
        assert path.parent == staging and path.name.startswith(spec.cell_id), path
        assert files == ["state.pt"]  # complete: written under a temp name, then renamed
    assert staging.is_dir() and not any(staging.iterdir()), "a staged checkpoint was left behind"
    # (torch may create its empty torchinductor_<user> cache dir there; no file is written)
    assert not [p for p in system_tmp.rglob("*") if p.is_file()], "a file was written to the system temp dir"
    assert reports[-1][0]["cell_done"] == 1 and store.is_done(sweep_dir, spec.domain, spec.method, spec.cell_id)


def test_a_data_error_is_recorded_once_not_retried_as_a_crash(trainable, monkeypatch):
    sweep_tune, config, spec, sweep_dir, _, reports = trainable

    def unreadable(*args, **kwargs):
        raise MNISTError("MNIST file /data/train-images.gz is unreadable (planted by the test)")

    from asp_dist.training import pipeline

    monkeypatch.setattr(pipeline, "run_unit", unreadable)  # what the worker's trial function calls
    sweep_tune.train_cell(config)  # returns: Tune sees a finished trial, not an error to retry
    assert reports == [({"cell_done": 0, "cells_written": 0, "cell_failed": 1, "cell_ids": spec.cell_id,
                         "pack_id": ""}, None)]
    failed = store.failed_cells(sweep_dir)
    assert list(failed) == [spec.cell_id]
    assert "MNISTError: MNIST file /data/train-images.gz is unreadable" in failed[spec.cell_id]["error"]


@pytest.mark.parametrize("plant", PLANTS)
def test_a_planted_checkpoint_runs_nothing_and_its_cell_starts_over(trainable, monkeypatch, tmp_path, plant, capsys):
    """A checkpoint Tune hands back is read with weights_only: a planted pickle is refused in one line, never
    run, and the cell trains from its start to the row an uninterrupted run writes."""
    from ray import tune

    sweep_tune, config, spec, sweep_dir, _, reports = trainable
    planted = tmp_path / "planted-checkpoint"
    planted.mkdir()
    (planted / "state.pt").write_bytes(PLANTS[plant](tmp_path / "ran"))
    monkeypatch.setattr(sweep_tune.tune, "get_checkpoint", lambda: tune.Checkpoint.from_directory(planted))
    sweep_tune.train_cell(config)
    assert not (tmp_path / "ran").exists(), "restoring the planted checkpoint ran its code"
    rows = store.read_rows(sweep_dir)
    assert list(rows["cell_id"]) == [spec.cell_id] and rows["resumed_from_step"].isna().all()
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("asp-dist: warning:")]
    assert len(warnings) == 1 and "refused unread" in warnings[0] and "starts over" in warnings[0], warnings


@pytest.mark.parametrize("bad", ["nan", "inf", "missing"])
def test_a_cell_without_finite_metrics_fails_in_one_line_and_resume_retries_it(trainable, monkeypatch, bad, capsys):
    """A row is finished only if every metric its domain declares is there and finite: otherwise no row is
    written, the failure is recorded under its cause, and the cell is pending again for `resume`."""
    from asp_dist.core.registry import get_domain
    from asp_dist.sweep.ledger import new_manifest

    sweep_tune, config, spec, sweep_dir, _, reports = trainable
    store.write_manifest(sweep_dir, new_manifest("smoke", "smoke", [spec.resolved()]))
    domain = get_domain(spec.domain)
    evaluate = domain.evaluate

    def broken(*args):
        metrics = dict(evaluate(*args))
        if bad == "missing":
            del metrics["mixed"]
        else:
            metrics["mixed"] = float(bad)
        return metrics

    monkeypatch.setattr(domain, "evaluate", broken)
    sweep_tune.train_cell(config)
    assert not store.is_done(sweep_dir, spec.domain, spec.method, spec.cell_id)
    error = store.failed_cells(sweep_dir)[spec.cell_id]["error"]
    why = {"nan": "metric 'mixed' is NaN", "inf": "metric 'mixed' is inf", "missing": "metric 'mixed' is missing"}
    assert error.startswith(f"InvalidRow: signaling evaluate gave no valid row: {why[bad]}"), error
    capsys.readouterr()
    assert cli.main(["status", sweep_dir.name, "--results", str(sweep_dir.parent)]) == 0
    assert f"1 cell: InvalidRow: signaling evaluate gave no valid row: {why[bad]}" in capsys.readouterr().out
    monkeypatch.setattr(domain, "evaluate", evaluate)  # the domain fixed: what resume then does with the cell
    sweep_tune.train_cell(config)
    assert store.is_done(sweep_dir, spec.domain, spec.method, spec.cell_id) and not store.failed_cells(sweep_dir)


# ---- stopping a running sweep --------------------------------------------------------------------------------
FAKE_DRIVER = """
import subprocess, sys, time
from asp_dist.sweep import tune
temp_dir = sys.argv[1]
reaper = tune._start_reaper(temp_dir)
# A node process (its command line names the temp dir) whose child renames nothing and names nothing:
# only the family tree says it is ours, as for Ray's agents after setproctitle.
node = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time; "
                         "c = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(600)']); "
                         "print(c.pid, flush=True); time.sleep(600)", temp_dir], stdout=subprocess.PIPE, text=True)
print(node.pid, node.stdout.readline().strip(), flush=True)
time.sleep(600)
"""


def test_the_reaper_kills_the_whole_family_of_a_killed_driver_and_nothing_else(tmp_path):
    temp_dir = str(tmp_path / "ray")
    bystander = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    driver = subprocess.Popen([sys.executable, "-c", FAKE_DRIVER, temp_dir], stdout=subprocess.PIPE, text=True,
                              env=env(), start_new_session=True)
    family = []
    try:
        family = [int(p) for p in driver.stdout.readline().split()]
        assert len(family) == 2, "the fake driver did not start its node process"
        log = Path(temp_dir, f"reaper-{driver.pid}.log")
        deadline = time.monotonic() + 30
        while "node process" not in (log.read_text() if log.exists() else "") and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.2)  # two more scans: the grandchild joins the tree
        driver.kill()
        driver.wait(10)
        deadline = time.monotonic() + 10
        while any(Path(f"/proc/{p}").exists() and b"zombie" not in _state(p) for p in family) \
                and time.monotonic() < deadline:
            time.sleep(0.1)
        alive = [p for p in family if Path(f"/proc/{p}").exists() and b"zombie" not in _state(p)]
        assert not alive, f"the reaper left {alive} running; its log: {log.read_text()}"
        assert bystander.poll() is None, "the reaper killed a process that was not the driver's"
        assert "killed" in log.read_text()
    finally:
        for pid in family:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        driver.kill()
        bystander.kill()
        bystander.wait()


def _state(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/status").read_bytes()
    except OSError:
        return b"zombie"


def start_smoke(tmp_path, ray_temp, *extra, command=("sweep", "smoke"), results=None):
    """`asp-dist sweep smoke` (or `command`) in the background, its stderr in tmp_path/driver.err."""
    err = open(tmp_path / "driver.err", "w")  # a file: a full pipe would block the driver
    driver = subprocess.Popen([sys.executable, "-m", "asp_dist.cli", *command, "--results",
                               str(results or tmp_path / "results"), "--ray-temp-dir", ray_temp, *extra],
                              env=env(), start_new_session=True, stdout=subprocess.DEVNULL, stderr=err)
    err.close()
    return driver


@pytest.mark.slow
@pytest.mark.parametrize("moment", ["ray-starting", "workers-starting"])
def test_sigterm_during_start_up_stops_the_sweep(tmp_path, moment):
    """A SIGTERM while the embedded Ray comes up (its GCS runs, ray.init has not returned) or while Tune starts
    the first workers stops the sweep as one during training does: exit 143, the one line, no process left
    (before: one sent while ray.init ran was lost, and the sweep finished with exit 0)."""
    ray_temp = f"/tmp/asp-ls-{os.getpid()}"
    driver = start_smoke(tmp_path, ray_temp)
    want = "gcs_server" if moment == "ray-starting" else "ray::"
    try:
        deadline = time.monotonic() + 120
        while driver.poll() is None and time.monotonic() < deadline and not any(
                process_name(pid).startswith(want) for pid in session_processes(driver.pid, ray_temp)):
            time.sleep(0.05)
        assert driver.poll() is None, "the sweep ended before it could be stopped"
        driver.send_signal(signal.SIGTERM)
        try:
            code = driver.wait(60)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the sweep did not stop within 60 s of a SIGTERM ({moment})")
        err = (tmp_path / "driver.err").read_text()
        assert code == 128 + signal.SIGTERM, err[-3000:]
        assert "asp-dist: interrupted (SIGTERM)" in err and "Traceback" not in err, err[-3000:]
        assert not wait_until_gone(driver.pid, ray_temp, 10)
        assert len(parquet_files(tmp_path / "results" / "smoke")) < 18
    finally:
        kill_all(driver.pid, ray_temp)
        import shutil

        shutil.rmtree(ray_temp, ignore_errors=True)


@pytest.fixture
def tiny_disk(tmp_path):
    """A 640 kB file system (tmpfs; needs root, as CI and the outside tester had): the smoke sweep fills it."""
    mount = tmp_path / "tiny"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=640k", "tmpfs", str(mount)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({made.stderr.decode().strip()})")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


@pytest.mark.slow
def test_a_full_disk_and_a_sigterm_each_stop_the_sweep_in_one_line_and_resume_finishes_it(tmp_path, tiny_disk):
    """A sweep that fills its disk stops in one line (exit 2, no traceback, every row it kept whole). Given space,
    its `resume` is stopped by SIGTERM after a cell: promptly, exit 143 and the interrupt's one line, no process
    of its Ray left, `status` says "not running". The next `resume` finishes it: every cell once, no finished
    cell rewritten, checkpoints taken and none left staged. (One sweep for both stops: a Ray start-up and a
    smoke sweep's cells cost the suite ≈ 30 CPU-s.)"""
    results = tiny_disk / "results"
    sweep_dir = results / "smoke"
    ray_temp = f"/tmp/asp-lf-{os.getpid()}"  # short: Ray's socket paths live under it

    def run(*args):
        return subprocess.run([sys.executable, "-m", "asp_dist.cli", *args, "--results", str(results),
                               "--ray-temp-dir", ray_temp], env=env(), capture_output=True, text=True, timeout=420,
                              start_new_session=True)

    try:
        full = run("sweep", "smoke")
        assert full.returncode == 2, full.stderr[-3000:]
        errors = [line for line in full.stderr.splitlines() if line.startswith("asp-dist: error:")]
        assert len(errors) == 1 and "no space left" in errors[0] and str(sweep_dir) in errors[0], full.stderr
        assert "Traceback" not in full.stderr and len(full.stderr.splitlines()) < 10, full.stderr[-3000:]
        kept = parquet_files(sweep_dir)
        assert 0 < len(kept) < 17, f"{len(kept)} cells fit: too few left to stop a resume between two of them"
        assert len(store.read_rows(sweep_dir, strict=True)) == len(kept), "a partial file was counted"
        first = {f: f.stat().st_mtime_ns for f in kept}

        subprocess.run(["mount", "-o", "remount,size=64m", str(tiny_disk)], check=True)
        driver = start_smoke(tmp_path, ray_temp, "--checkpoint-every", "0.2", command=("resume", "smoke"),
                             results=results)
        try:
            wait_for(lambda: len(parquet_files(sweep_dir)) > len(kept), 300, poll_s=0.1, while_alive=driver,
                     what="a cell of the resume finished")
            driver.send_signal(signal.SIGTERM)
            stopped = time.monotonic()
            try:
                code = driver.wait(30)
            except subprocess.TimeoutExpired:
                pytest.fail("the sweep did not stop within 30 s of SIGTERM")
            err = (tmp_path / "driver.err").read_text()
            assert code == 128 + signal.SIGTERM, err[-3000:]
            assert "asp-dist: interrupted (SIGTERM); finished cells are kept: asp-dist resume smoke" in err
            left = wait_until_gone(driver.pid, ray_temp, 10)
            assert not left, f"left running {time.monotonic() - stopped:.0f} s after SIGTERM: {left}"
        finally:
            kill_all(driver.pid, ray_temp)
        first.update({f: f.stat().st_mtime_ns for f in parquet_files(sweep_dir) if f not in first})
        assert len(kept) < len(first) < 18
        assert "not running" in ledger.sweep_status("smoke", results)

        resumed = run("resume", "smoke", "--checkpoint-every", "0.2")
        assert resumed.returncode == 0, resumed.stderr[-3000:]
        assert "Traceback" not in resumed.stderr, resumed.stderr[-3000:]
        assert "18/18 cells done, 0 failed" in resumed.stdout
    finally:
        import shutil

        shutil.rmtree(ray_temp, ignore_errors=True)
    files = parquet_files(sweep_dir)
    df = store.read_rows(sweep_dir, strict=True)
    assert len(files) == 18 and len(df) == 18 and df["cell_id"].is_unique  # every cell exactly once
    assert set(df["cell_id"]) == {s.cell_id for s in expand("smoke")}
    assert all(f.stat().st_mtime_ns == m for f, m in first.items()), "a finished cell was written again"
    assert not store.failed_cells(sweep_dir)
    assert list((sweep_dir / "tune").glob("run-*/*/checkpoint_*")), "no checkpoint was taken"
    staging = sweep_dir / "tune" / ".ckpt-tmp"
    assert not staging.exists() or not any(staging.iterdir()), "staged checkpoints were left behind"
