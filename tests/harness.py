"""What the end-to-end tests share: running the CLI as a user would, processes and ports, sweep layouts,
rows an uninterrupted run gives, and Ray clusters on loopback.

Every sweep runs as a CLI subprocess of this interpreter (`python -m asp_dist.cli`), in its own session,
so a killed driver cannot take pytest with it and its process group can be killed in teardown. Tools are
found next to sys.executable (the venv's `ray`), never on PATH.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import pickle
import re
import secrets
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Iterator

RAY = str(Path(sys.executable).with_name("ray"))  # this interpreter's Ray, not whatever is on PATH
CLUSTER_TOKEN = secrets.token_hex(16)  # Ray's token authentication for the clusters the tests start
# Differ between two runs of one spec beyond row.VOLATILE_COLUMNS: where and by which sweep it ran, and
# the working tree's revision (other engineers commit while tests run).
PLACE_COLUMNS = {"sweep_id", "ray_node_id", "ray_version", "code_revision"}


# ---- processes ------------------------------------------------------------------------------------------
def env(base: dict[str, str] | None = None, **extra: str | None) -> dict[str, str]:
    """The environment of a CLI subprocess: `base` (default: this process's), one thread per process, no
    usage stats, unbuffered output, then `extra` (a None value removes that variable)."""
    e = dict(os.environ if base is None else base, OMP_NUM_THREADS="1", RAY_USAGE_STATS_ENABLED="0",
             PYTHONUNBUFFERED="1")
    e.update(extra)
    return {k: v for k, v in e.items() if v is not None}


def token_env(base: dict[str, str] | None = None, **extra: str | None) -> dict[str, str]:
    """env() for a cluster's nodes and a driver that joins it: token authentication on (cluster/README.md)."""
    return env(base, RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=CLUSTER_TOKEN, **extra)


def cli(*args: str, timeout: float = 420, cwd: str | Path | None = None, base_env: dict[str, str] | None = None,
        **extra_env: str | None) -> subprocess.CompletedProcess:
    """`asp-dist ARGS` in a subprocess of this interpreter, in its own session; output captured."""
    return subprocess.run([sys.executable, "-m", "asp_dist.cli", *args], env=env(base_env, **extra_env),
                          capture_output=True, text=True, timeout=timeout, start_new_session=True, cwd=cwd)


def start_cli(*args: str, log_dir: Path, base_env: dict[str, str] | None = None, cwd: str | Path | None = None,
              **extra_env: str | None) -> subprocess.Popen:
    """`asp-dist ARGS` started in the background; its output goes to log_dir/out and log_dir/err (files: a
    full pipe would block the driver). read_log(log_dir) reads them back."""
    log_dir.mkdir(parents=True, exist_ok=True)
    with open(log_dir / "out", "w") as out, open(log_dir / "err", "w") as err:
        return subprocess.Popen([sys.executable, "-m", "asp_dist.cli", *args], env=env(base_env, **extra_env),
                                stdout=out, stderr=err, start_new_session=True, cwd=cwd)


# ---- the processes of a driver's Ray ----------------------------------------------------------------------
def process_name(pid: int) -> str:
    """A process's name (/proc/PID/comm, 15 bytes: "ray::ImplicitFu"), "?" once it is gone."""
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return "?"


def python_program(pid: int) -> str | None:
    """The script a Python process runs (the basename of its first `*.py` argument: "setup_worker.py"), if any."""
    try:
        args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    return next((Path(a.decode(errors="replace")).name for a in args[1:4] if a.endswith(b".py")), None)


def process_environ(pid: int) -> dict[str, str]:
    """A process's environment as it started (/proc/PID/environ), {} once it is gone."""
    try:
        raw = Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:
        return {}
    return dict(item.decode(errors="replace").split("=", 1) for item in raw.split(b"\0") if b"=" in item)


def session_processes(sid: int, ray_temp: str) -> dict[int, str]:
    """Processes started by the driver (its session: start_new_session) or naming this test's Ray temp dir."""
    found = {}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            if os.getsid(int(proc.name)) == sid or ray_temp in cmdline:
                found[int(proc.name)] = cmdline[:100]
        except OSError:
            continue
    return found


def wait_until_gone(sid: int, ray_temp: str, seconds: float) -> dict[int, str]:
    deadline = time.monotonic() + seconds
    while (left := session_processes(sid, ray_temp)) and time.monotonic() < deadline:
        time.sleep(0.2)
    return left


def kill_all(sid: int, ray_temp: str) -> None:
    for pid in session_processes(sid, ray_temp):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def read_log(log_dir: Path) -> tuple[str, str]:
    return (log_dir / "out").read_text(), (log_dir / "err").read_text()


def kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL the process group of a CLI started by cli()/start_cli() (the Ray processes it started too)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(condition, seconds: float, *, poll_s: float = 0.05, while_alive: subprocess.Popen | None = None,
             what: str = "the condition") -> Any:
    """Poll `condition()` until it is truthy (returned), the deadline passes or `while_alive` ends (an
    AssertionError either way): tests wait for the state they need, never a fixed time."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        if while_alive is not None and while_alive.poll() is not None:
            raise AssertionError(f"the process ended (exit {while_alive.returncode}) before {what}")
        time.sleep(poll_s)
    raise AssertionError(f"{what} did not happen within {seconds:g} s")


# ---- sweep layouts --------------------------------------------------------------------------------------
# The grid the driver-kill tests (disk and S3) interrupt: 4 cells of about 1.5 s each on one core, two at a
# time, with checkpoints every 0.3 s, so that a cell is mid-run with a persisted checkpoint while others are
# done (the tests wait for exactly that state). Two trials: two bases, so resume also reads a cached one.
KILL_GRID = """
[[grid]]
fixed = { train_steps = 1500, unpaired_size = 256 }
axes = { domain = ["signaling"], method = ["osp", "asp"], paired = [2], trial = [0, 1] }
"""


def space(tmp_path: Path, text: str, name: str = "grid.toml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def parquet_files(sweep_dir: str | Path) -> list[Path]:
    return sorted(Path(sweep_dir, "cells").glob("domain=*/method=*/*.parquet"))


def checkpointed_running_trials(state_text: str) -> dict[str, int]:
    """Trial directory name (a cell's or a pack's) -> index of its checkpoint, for each trial that a Tune
    experiment state (the JSON text of experiment_state-*.json) holds as RUNNING with a checkpoint: the trials
    a restore from that state continues from a checkpoint. Tune snapshots its state every few seconds and,
    under load, well after a checkpoint appears; waiting on what the state says, not on file times, keeps the
    kill tests from killing too early. (The checkpoint manager is pickled into the state: its newest
    checkpoint's path is in the pickle's bytes.)"""
    try:
        trials = json.loads(state_text)["trial_data"]
    except (ValueError, KeyError, TypeError):  # a state file caught mid-write
        return {}
    found = {}
    for trial, meta in trials:
        trial, meta = json.loads(trial), json.loads(meta)
        pickled = bytes.fromhex((meta.get("checkpoint_manager") or {}).get("value", ""))
        indices = [int(i) for i in re.findall(rb"checkpoint_(\d{6})", pickled)]
        if trial.get("status") == "RUNNING" and indices:
            found[trial["config"]["cell"]["name"]] = max(indices)
    return found


def newest_state(experiment_dir: Path) -> str:
    """The JSON text of the newest Tune experiment state in a local experiment directory ("" when none)."""
    states = sorted(Path(experiment_dir).glob("experiment_state-*.json"))
    return states[-1].read_text() if states else ""


def ray_workers_running(cell_id: str, ray_temp_dir: str) -> list[int]:
    """Pids of the Ray workers of this test's Ray running `cell_id`: Tune moves a trial's worker into the
    trial's working directory, named after the cell (trial_dirname_creator), also when it reuses an actor."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            cwd = os.readlink(proc / "cwd")
        except (OSError, ValueError):
            continue
        if proc.name.isdigit() and cwd.startswith(ray_temp_dir) and Path(cwd).name == cell_id:
            pids.append(int(proc.name))
    return pids


def hold_a_running_cell_at_its_checkpoint(read_state, checkpoint_exists, done, ray_temp: str, seconds: float,
                                          driver: subprocess.Popen) -> str:
    """Wait until Tune's experiment state (`read_state()`: the newest state's JSON text, or "") names a checkpoint
    of a running cell not in `done()` that exists (`checkpoint_exists(cell, index)`), then SIGSTOP that cell's
    workers, so that no newer checkpoint replaces (and deletes) it before the driver is killed; returns the cell.

    Tune deletes a trial's older checkpoint when it registers a newer one, and uploads its experiment state to
    remote storage asynchronously: a kill at an arbitrary moment may leave a state naming a deleted checkpoint
    (the trial then starts over: tests/test_pack_sweep.py). Freezing the cell makes "killed while resumable"
    a state the test waits for, not a moment it hopes to hit."""
    deadline = time.monotonic() + seconds
    stopped: set[str] = set()
    while time.monotonic() < deadline:
        if driver.poll() is not None:
            raise AssertionError(f"the sweep ended (exit {driver.returncode}) before a cell could be held")
        finished = set(done())
        named = {c for c, i in checkpointed_running_trials(read_state()).items() if checkpoint_exists(c, i)} - finished
        if named & stopped:  # frozen, and the state names its checkpoint: resumable whenever the kill comes
            return sorted(named & stopped)[0]
        for cell in named - stopped:
            for pid in ray_workers_running(cell, ray_temp):
                try:
                    os.kill(pid, signal.SIGSTOP)
                except ProcessLookupError:
                    continue
                stopped.add(cell)
        time.sleep(0.1)
    raise AssertionError(f"no running cell with a checkpoint in Tune's state within {seconds:g} s")


def finished_row(spec, **values: Any) -> dict[str, Any]:
    """A result row made by hand (no training) that the store counts as finished: the spec's columns, its cell id
    and every metric a row must have finite (0.5 each unless `values` say otherwise)."""
    from asp_dist.core.contract import REQUIRED_METRICS

    return {**spec.to_dict(), "cell_id": spec.cell_id, **{f"eval_{m}": 0.5 for m in REQUIRED_METRICS}, **values}


def fingerprint(root: Path) -> dict[str, str | None]:
    """path -> content hash of every file under `root` (None for a directory): "nothing was written"."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None
            for p in sorted(root.rglob("*"))}


# ---- rows -------------------------------------------------------------------------------------------------
def clean(value: Any) -> Any:
    """Parquet gives NaN for a null float and numpy scalars; compare as plain Python values."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return value.item() if hasattr(value, "item") else value


_EXPECTED: dict[str, dict[str, Any]] = {}  # cell id -> its uninterrupted row (this process)
# Where the xdist workers of one run share those rows (conftest sets it; None: this process only). The disk and
# S3 kill tests run the same grid, and the killed-worker test one of its cells, usually on different workers.
SHARED_EXPECTED_DIR: Path | None = None


def expected_rows(specs) -> dict[str, dict[str, Any]]:
    """The rows an uninterrupted run_cell gives, without volatile and place columns; computed once per cell
    and test run (the rows are deterministic: whichever worker computes a cell, the others read it)."""
    for s in specs:
        if s.cell_id not in _EXPECTED:
            _EXPECTED[s.cell_id] = _shared_expected_row(s) if SHARED_EXPECTED_DIR else _expected_row(s)
    return {s.cell_id: _EXPECTED[s.cell_id] for s in specs}


def _expected_row(spec) -> dict[str, Any]:
    from asp_dist.training.cell import run_cell
    from asp_dist.training.row import comparable

    return {k: clean(v) for k, v in comparable(run_cell(spec)).items() if k not in PLACE_COLUMNS}


def _shared_expected_row(spec) -> dict[str, Any]:
    """The cell's row from the run's shared directory, computed here first if no worker has (under a lock:
    a worker that asks while another computes waits for it instead of training the cell again)."""
    from filelock import FileLock

    SHARED_EXPECTED_DIR.mkdir(parents=True, exist_ok=True)
    path = SHARED_EXPECTED_DIR / f"{spec.cell_id}.pickle"
    with FileLock(f"{path}.lock", timeout=900):
        if not path.is_file():
            row = _expected_row(spec)
            path.with_suffix(".tmp").write_bytes(pickle.dumps(row))
            path.with_suffix(".tmp").replace(path)
        return pickle.loads(path.read_bytes())


def comparable_rows(df) -> dict[str, dict[str, Any]]:
    """A sweep's rows as expected_rows gives them, by cell id."""
    from asp_dist.training.row import comparable

    return {r["cell_id"]: {k: clean(v) for k, v in comparable(r).items() if k not in PLACE_COLUMNS}
            for r in df.to_dict("records")}


def assert_rows_match(df, expected: dict[str, dict[str, Any]]):
    """Every expected cell exactly once, each row equal to the uninterrupted run's (bit for bit)."""
    assert len(df) == len(expected) and df["cell_id"].is_unique
    assert set(df["cell_id"]) == set(expected)
    got = comparable_rows(df)
    for cell_id, row in expected.items():
        assert {k: got[cell_id].get(k) for k in row} == row, cell_id
    return df


# ---- Ray clusters on loopback ----------------------------------------------------------------------------
WAIT_NODES = """import ray, sys, time
ray.init(address=sys.argv[1], logging_level='ERROR')
t = time.time()
while sum(n['Alive'] for n in ray.nodes()) < int(sys.argv[2]) and time.time() - t < 120:
    time.sleep(0.5)
print(sum(n['Alive'] for n in ray.nodes()))
"""


@contextmanager
def ray_cluster(temps: list[str], *, base_env: dict[str, str] | None = None,
                cwds: list[Path] | None = None) -> Iterator[SimpleNamespace]:
    """A Ray cluster of len(temps) one-CPU nodes on this machine (a head, then workers joining it), each with
    its own temp dir (and working directory), token authentication on: .address, .env (what a driver
    joining it needs). Only the processes started here are stopped at the end (never `ray stop`)."""
    port = free_port()
    address = f"127.0.0.1:{port}"
    # No drain on SIGTERM (Ray waits up to 30 s for Serve-like components; a test cluster has none).
    node_env = token_env(base_env, RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S="0")
    common = ["--num-cpus=1", "--block", "--disable-usage-stats", "--node-ip-address=127.0.0.1",
              "--object-store-memory=100000000"]
    cwds = cwds or [None] * len(temps)
    procs = []

    def nodes_alive(n: int) -> bool:
        probe = subprocess.run([sys.executable, "-c", WAIT_NODES, address, str(n)], env=node_env, capture_output=True,
                               text=True, timeout=180, cwd=cwds[0])
        return probe.stdout.strip() == str(n)

    try:
        procs.append(subprocess.Popen([RAY, "start", "--head", f"--port={port}", "--include-dashboard=false",
                                       f"--temp-dir={temps[0]}", *common], env=node_env, cwd=cwds[0],
                                      start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        wait_for(lambda: nodes_alive(1), 120, poll_s=0.5, what="the Ray head accepting connections")
        for temp, cwd in zip(temps[1:], cwds[1:]):
            procs.append(subprocess.Popen([RAY, "start", f"--address={address}", f"--temp-dir={temp}", *common],
                                          env=node_env, cwd=cwd, start_new_session=True, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
        assert nodes_alive(len(temps)), "not every Ray node joined"
        yield SimpleNamespace(address=address, env=node_env, temps=[Path(t) for t in temps])
    finally:
        for p in reversed(procs):  # `ray start --block` stops its node on SIGTERM
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                pass
            kill_group(p)
            p.wait(10)
        for t in temps:
            subprocess.run(["rm", "-rf", t])


# ---- an S3 server on loopback ------------------------------------------------------------------------------
S3_REGION = "us-east-1"


def s3_env(**extra: str) -> dict[str, str]:
    """env() without the caller's AWS settings (no profile, no instance metadata): only what a test gives."""
    e = env({k: v for k, v in os.environ.items() if not k.startswith("AWS_")}, AWS_DEFAULT_REGION=S3_REGION,
            AWS_REGION=S3_REGION, AWS_EC2_METADATA_DISABLED="true", AWS_CONFIG_FILE="/nonexistent",
            AWS_SHARED_CREDENTIALS_FILE="/nonexistent")
    e.update(extra)
    return e


def start_moto(log: Path, authenticate: bool = False) -> tuple[subprocess.Popen, str]:
    """moto's S3 server (a real HTTP server) on a free loopback port; (process, endpoint URL)."""
    port = free_port()
    server_env = s3_env()
    if authenticate:
        server_env["INITIAL_NO_AUTH_ACTION_COUNT"] = "3"  # the IAM user, its policy and its key; the rest is checked
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                                env=server_env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)

    def answers() -> bool:
        if proc.poll() is not None:
            raise RuntimeError(f"moto server exited: {log.read_text()[-2000:]}")
        try:
            socket.create_connection(("127.0.0.1", port), 0.2).close()
            return True
        except OSError:
            return False

    try:
        wait_for(answers, 60, poll_s=0.1, what="the moto server accepting connections")
    except AssertionError:
        stop_now(proc)
        raise
    return proc, f"http://127.0.0.1:{port}"


def stop_now(proc: subprocess.Popen) -> None:
    """SIGKILL a server's process group and reap it."""
    kill_group(proc)
    proc.wait(10)
