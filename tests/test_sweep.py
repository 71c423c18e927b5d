"""The sweep service end to end on real Ray: smoke sweep, SIGKILL of the driver then resume,
a worker killed mid-cell, a cell that keeps failing, and a two-node Ray cluster on loopback.

Every sweep runs as a CLI subprocess (as a user would), so a killed driver cannot take pytest
with it; processes started here run in their own sessions and are killed in teardown.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from asp_dist.results import store
from asp_dist.sweep.spaces import expand
from asp_dist.sweep.tune import FAULT_ENV
from asp_dist.training.cell import run_cell
from asp_dist.training.row import comparable
from asp_dist.training.row import schema as row_schema

pytestmark = pytest.mark.slow

# Differ between two runs of one spec beyond cell.VOLATILE_COLUMNS: where and by which sweep it
# ran, and the working tree's revision (other engineers commit while tests run).
PLACE_COLUMNS = {"sweep_id", "ray_node_id", "ray_version", "code_revision"}


def env(**extra):
    e = dict(os.environ, OMP_NUM_THREADS="1", RAY_USAGE_STATS_ENABLED="0", PYTHONUNBUFFERED="1")
    e.pop(FAULT_ENV, None)
    e.update(extra)
    return e


def cli(*args, timeout=420, **extra_env):
    proc = subprocess.run([sys.executable, "-m", "asp_dist.cli", *args], env=env(**extra_env), capture_output=True,
                          text=True, timeout=timeout, start_new_session=True)
    return proc


def space(tmp_path, text, name="grid.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def clean(value):
    """Parquet gives NaN for a null float and numpy scalars; compare as plain Python values."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return value.item() if hasattr(value, "item") else value


def expected_rows(specs):
    return {s.cell_id: {k: clean(v) for k, v in comparable(run_cell(s)).items() if k not in PLACE_COLUMNS}
            for s in specs}


def assert_rows_match(sweep_dir, expected):
    df = store.read_rows(sweep_dir)
    assert len(df) == len(expected) and df["cell_id"].is_unique
    assert set(df["cell_id"]) == set(expected)
    for rec in df.to_dict("records"):
        got = {k: clean(v) for k, v in comparable(rec).items() if k in expected[rec["cell_id"]]}
        assert got == expected[rec["cell_id"]], rec["cell_id"]
    return df


def kill_group(proc):
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def parquet_files(sweep_dir):
    return sorted(p for p in Path(sweep_dir, "cells").glob("domain=*/method=*/*.parquet"))


def test_smoke_sweep_end_to_end(tmp_path):
    proc = cli("sweep", "smoke", "--results", str(tmp_path))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "18/18 cells done, 0 failed" in proc.stdout
    sweep_dir = tmp_path / "smoke"
    files = parquet_files(sweep_dir)
    assert len(files) == 18
    for f in files:
        assert pq.read_schema(f).remove_metadata() == row_schema()
    df = store.read_rows(sweep_dir)
    assert len(df) == 18 and df["cell_id"].is_unique
    assert set(df["cell_id"]) == {s.cell_id for s in expand("smoke")}
    assert (df["sweep_id"] == "smoke").all() and df["ray_node_id"].notna().all()
    assert df["eval_mixed"].between(0, 1).all()
    assert df.groupby("trial")["base_key"].nunique().eq(1).all()
    assert len(list((sweep_dir / "bases").glob("*.pt"))) == 2, "one base per trial, shared by its 9 cells"
    assert "done" in proc.stderr and "ETA" in proc.stderr  # progress lines
    # Running it again retrains nothing and touches no file.
    mtimes = {f: f.stat().st_mtime_ns for f in files}
    again = cli("sweep", "smoke", "--results", str(tmp_path))
    assert again.returncode == 0 and "18 already done" in again.stderr
    assert {f: f.stat().st_mtime_ns for f in parquet_files(sweep_dir)} == mtimes
    status = cli("status", "smoke", "--results", str(tmp_path))
    assert status.stdout.splitlines()[-1].split() == ["total", "18", "0", "0"]


def test_sigkill_of_driver_then_resume(tmp_path):
    grid = space(tmp_path, """
[[grid]]
fixed = { train_steps = 4000, unpaired_size = 256 }
axes = { domain = ["signaling"], method = ["osp", "asp"], paired = [0, 2], trial = [0, 1] }
""")
    specs = expand(grid)
    results = tmp_path / "results"
    driver = subprocess.Popen([sys.executable, "-m", "asp_dist.cli", "sweep", grid, "--name", "k", "--results",
                               str(results), "--checkpoint-every", "0.3"], env=env(), start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not parquet_files(results / "k") and time.monotonic() < deadline and driver.poll() is None:
            time.sleep(0.2)
        # Cells last ~4 s on a fast core: 1.5 s after the first row, the next cells are mid-run and
        # have checkpointed (every 0.3 s). Shorter cells made this flaky on faster machines.
        time.sleep(1.5)
        assert driver.poll() is None, "the sweep finished before it could be interrupted"
        driver.send_signal(signal.SIGKILL)
        driver.wait(30)
    finally:
        kill_group(driver)  # Ray processes the killed driver started
    done_at_kill = len(parquet_files(results / "k"))
    assert 1 <= done_at_kill < len(specs)
    status = cli("status", "k", "--results", str(results))
    assert "not running" in status.stdout and f"total{'':<15}{done_at_kill:>7}" in status.stdout

    resumed = cli("resume", "k", "--results", str(results), "--checkpoint-every", "0.3")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"({done_at_kill} already done)" in resumed.stderr
    df = assert_rows_match(results / "k", expected_rows(specs))
    # Cells running at the kill continued from their checkpoints instead of starting over.
    assert df["resumed_from_step"].notna().any(), df[["cell_id", "resumed_from_step"]]
    assert not store.failed_cells(results / "k")


def test_killed_worker_is_retried_and_failing_cells_do_not_stop_the_sweep(tmp_path):
    grid = space(tmp_path, """
[[grid]]
fixed = { train_steps = 400, unpaired_size = 256, method = "asp", trial = 0 }
axes = { paired = [0, 2, 4, 8] }
""")
    specs = expand(grid)
    by_paired = {s.paired: s.cell_id for s in specs}
    marker = tmp_path / "killed-once"
    fault = f"{by_paired[2]}:150:{marker},{by_paired[4]}:50:always,{by_paired[8]}:50:raise"
    first = cli("sweep", grid, "--name", "f", "--results", str(tmp_path), "--max-failures", "1",
                "--checkpoint-every", "0.2", **{FAULT_ENV: fault})
    assert first.returncode == 1, first.stderr[-3000:]
    assert "2/4 cells done, 2 failed" in first.stdout
    assert marker.exists(), "the worker of the p2 cell was not killed"
    done = store.read_rows(tmp_path / "f")
    assert set(done["cell_id"]) == {by_paired[0], by_paired[2]}, "the killed worker's cell did not complete"
    failed = store.failed_cells(tmp_path / "f")
    assert set(failed) == {by_paired[4], by_paired[8]}
    assert "failed after 2 attempt(s)" in failed[by_paired[4]]["error"]  # worker died twice: 1 retry
    assert "BaseRejected: injected" in failed[by_paired[8]]["error"]  # deterministic: no retry
    status = cli("status", "f", "--results", str(tmp_path)).stdout
    assert status.splitlines()[-3].split() == ["total", "2", "2", "0"] and f"failed {by_paired[4]}" in status

    # resume retries the failed cells (the faults are gone) and never touches finished ones: the
    # worker-killed cell in the restored Tune experiment, the deterministic one in a fresh one.
    mtimes = {f: f.stat().st_mtime_ns for f in parquet_files(tmp_path / "f")}
    second = cli("resume", "f", "--results", str(tmp_path))
    assert second.returncode == 0, second.stderr[-3000:]
    assert all(f.stat().st_mtime_ns == m for f, m in mtimes.items())
    assert not store.failed_cells(tmp_path / "f")
    assert (tmp_path / "f" / "tune" / "run-2").is_dir()
    assert_rows_match(tmp_path / "f", expected_rows(specs))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def two_node_cluster(tmp_path):
    port = free_port()
    address = f"127.0.0.1:{port}"
    common = ["--num-cpus=1", "--block", "--disable-usage-stats", "--node-ip-address=127.0.0.1",
              "--object-store-memory=100000000"]
    head = subprocess.Popen(["ray", "start", "--head", f"--port={port}", "--include-dashboard=false",
                             "--temp-dir=/tmp/asp-rt-h", *common], env=env(), start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [head]
    try:
        wait_nodes = ("import ray, time, sys\n"
                      f"ray.init(address='{address}', logging_level='ERROR')\n"
                      "t = time.time()\n"
                      "while sum(n['Alive'] for n in ray.nodes()) < int(sys.argv[1]) and time.time() - t < 120:\n"
                      "    time.sleep(0.5)\n"
                      "print(sum(n['Alive'] for n in ray.nodes()))\n")
        for attempt in range(60):  # the head takes a while to accept connections
            probe = subprocess.run([sys.executable, "-c", wait_nodes, "1"], env=env(), capture_output=True,
                                   text=True, timeout=180)
            if probe.stdout.strip() == "1":
                break
            time.sleep(1)
        procs.append(subprocess.Popen(["ray", "start", f"--address={address}", "--temp-dir=/tmp/asp-rt-w", *common],
                                      env=env(), start_new_session=True, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
        probe = subprocess.run([sys.executable, "-c", wait_nodes, "2"], env=env(), capture_output=True, text=True,
                               timeout=180)
        assert probe.stdout.strip() == "2", probe.stderr[-2000:]
        yield address
    finally:
        for p in reversed(procs):
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        time.sleep(2)
        for p in procs:
            kill_group(p)
            p.wait(10)


def test_two_node_cluster_via_address(tmp_path, two_node_cluster):
    grid = space(tmp_path, """
[[grid]]
fixed = { train_steps = 300, unpaired_size = 256 }
axes = { domain = ["signaling"], method = ["osp", "asp"], paired = [0, 2, 4] }
""")
    proc = cli("sweep", grid, "--name", "c", "--results", str(tmp_path / "results"), "--address", two_node_cluster,
               "--workers", "2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"cluster {two_node_cluster}" in proc.stderr
    df = store.read_rows(tmp_path / "results" / "c")
    assert len(df) == 6 and df["cell_id"].is_unique
    assert df["ray_node_id"].nunique() == 2, df[["cell_id", "ray_node_id"]]
