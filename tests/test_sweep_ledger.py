"""The sweep ledger without Ray: names, the directory check, the lock (also after SIGKILL), status
reading a running sweep without disturbing it, SIGTERM as Ctrl-C, the manifest against the grid,
specs from the manifest, and the status text."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from harness import finished_row

from asp_dist.errors import SchemaError, SweepError
from asp_dist.results import store
from asp_dist.sweep import ledger, preflight, signals
from asp_dist.sweep.spaces import expand


@pytest.fixture(scope="module")
def smoke_specs():
    return expand("smoke")


def test_names_are_plain_directory_names(tmp_path):
    assert ledger.sweep_dir_for(tmp_path, "exp-1.b_2") == tmp_path.resolve() / "exp-1.b_2"
    for bad in ("../up", "a/b", ".hidden", "", "x" * 65):
        with pytest.raises(SweepError, match="invalid sweep name"):
            ledger.sweep_dir_for(tmp_path, bad)


def test_a_directory_that_is_not_a_sweep_is_refused(tmp_path, smoke_specs):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(SweepError, match="is not a sweep"):
        preflight.check_sweep_dir(foreign)
    preflight.check_sweep_dir(tmp_path / "new")  # created, and writable
    store.write_manifest(tmp_path / "new", ledger.new_manifest("new", "smoke", smoke_specs))
    (tmp_path / "new" / "stray.txt").write_text("x")
    preflight.check_sweep_dir(tmp_path / "new")  # a sweep may hold other files


def test_lock_refuses_a_second_run_and_dies_with_its_holder(tmp_path):
    with ledger.sweep_lock(tmp_path):
        assert ledger.lock_holder(tmp_path).startswith(f"pid {os.getpid()} on ")
        with pytest.raises(SweepError, match="is already running \\(pid"):
            with ledger.sweep_lock(tmp_path):
                pass
    assert ledger.lock_holder(tmp_path) is None
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path\n"
                               "from asp_dist.sweep.ledger import sweep_lock\n"
                               "with sweep_lock(Path(sys.argv[1])):\n"
                               "    print('locked', flush=True); time.sleep(600)\n", str(tmp_path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert ledger.lock_holder(tmp_path).startswith(f"pid {holder.pid} on ")
        holder.send_signal(signal.SIGKILL)
        holder.wait(30)
    finally:
        holder.kill()
    deadline = time.monotonic() + 10
    while ledger.lock_holder(tmp_path) is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert ledger.lock_holder(tmp_path) is None, "a killed holder's lock was not released"
    with ledger.sweep_lock(tmp_path):
        pass


PROBE_LOOP = """import sys, time
from pathlib import Path
from asp_dist.sweep.ledger import lock_holder
print('probing', flush=True)
end = time.monotonic() + float(sys.argv[2])
n = 0
while time.monotonic() < end:
    lock_holder(Path(sys.argv[1]))
    n += 1
print(n, flush=True)
"""


def test_status_reads_a_running_sweep_without_blocking_or_refusing_it(tmp_path, smoke_specs):
    sweep_dir = tmp_path / "exp"
    sweep_dir.mkdir()
    store.write_manifest(sweep_dir, ledger.new_manifest("exp", "smoke", smoke_specs))
    assert "not running" in ledger.sweep_status("exp", tmp_path)
    assert not (sweep_dir / ledger.LOCK_FILE).exists(), "status created the lock file"

    # A run holding the lock in another process: status answers at once, names it, and changes nothing.
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path\n"
                               "from asp_dist.sweep.ledger import sweep_lock\n"
                               "with sweep_lock(Path(sys.argv[1])):\n"
                               "    print('locked', flush=True); time.sleep(600)\n", str(sweep_dir)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        lock_text = (sweep_dir / ledger.LOCK_FILE).read_bytes()
        # (It probes the lock without waiting, LOCK_NB: a blocking probe would never return while the run lasts.)
        text = ledger.sweep_status("exp", tmp_path)
        assert f"RUNNING (pid {holder.pid} on " in text.splitlines()[0]
        assert (sweep_dir / ledger.LOCK_FILE).read_bytes() == lock_text
    finally:
        holder.kill()
        holder.wait(30)

    # Another status probing at the same time (a shared lock) is not a run: status says "not running",
    # and a run starting meanwhile is not refused.
    import fcntl

    with open(sweep_dir / ledger.LOCK_FILE) as other_status:
        fcntl.flock(other_status, fcntl.LOCK_SH | fcntl.LOCK_NB)
        assert ledger.lock_holder(sweep_dir) is None
        assert "not running" in ledger.sweep_status("exp", tmp_path)
        fcntl.flock(other_status, fcntl.LOCK_UN)

    # status polled in a tight loop by another process never makes a starting run refuse (before: the
    # probe took the exclusive lock, and a run starting during a probe was told the sweep was running).
    prober = subprocess.Popen([sys.executable, "-c", PROBE_LOOP, str(sweep_dir), "6"], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert prober.stdout.readline().strip() == "probing"
        starts = 0
        while prober.poll() is None and starts < 200:
            with ledger.sweep_lock(sweep_dir):
                starts += 1
        probes = int(prober.stdout.readline())
    finally:
        prober.kill()
        prober.wait(30)
    assert starts >= 20 and probes >= 100, (starts, probes)


def test_sigterm_stops_a_sweep_like_ctrl_c(monkeypatch):
    previous = signal.getsignal(signal.SIGTERM)
    with signals.sigterm_as_interrupt():
        assert signal.getsignal(signal.SIGTERM) is signals._sigterm
        with signals.sigterm_as_interrupt():  # nested: a no-op
            pass
        assert signal.getsignal(signal.SIGTERM) is signals._sigterm
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        assert signals.interrupted_by == signal.SIGTERM
        # While Tune runs it owns SIGINT (a graceful stop): SIGTERM goes the same way.
        tune_stops = []
        monkeypatch.setattr(signal, "getsignal", lambda s, real=signal.getsignal:
                            (lambda n, f: tune_stops.append(n)) if s == signal.SIGINT else real(s))
        signals._sigterm(signal.SIGTERM, None)
        assert tune_stops == [signal.SIGINT]
        # A background job ignores SIGINT; SIGTERM still stops it.
        monkeypatch.setattr(signal, "getsignal", lambda s, real=signal.getsignal:
                            signal.SIG_IGN if s == signal.SIGINT else real(s))
        with pytest.raises(KeyboardInterrupt):
            signals._sigterm(signal.SIGTERM, None)
        monkeypatch.undo()
    assert signal.getsignal(signal.SIGTERM) is previous


def test_manifest_keeps_the_grid_and_refuses_another(tmp_path, smoke_specs):
    first = preflight.check_manifest(tmp_path, "exp", smoke_specs, "smoke")
    assert first["cells"] == [s.cell_id for s in smoke_specs] and first["space"] == "smoke"
    store.write_manifest(tmp_path, first)
    assert preflight.check_manifest(tmp_path, "exp", list(reversed(smoke_specs)), "smoke") == first  # order-free
    with pytest.raises(SweepError, match="was started with another grid .* 18 cells.* now 'other', 17 cells"):
        preflight.check_manifest(tmp_path, "exp", smoke_specs[1:], "other")
    assert ledger.specs_from_manifest(store.read_manifest(tmp_path)) == smoke_specs


def test_specs_that_no_longer_resolve_to_their_ids_are_refused(smoke_specs):
    manifest = json.loads(json.dumps(ledger.new_manifest("exp", "smoke", smoke_specs[:2])))
    manifest["cells"][1] = "signaling-asp-p0-t0-0000000000"  # what a changed default would do
    with pytest.raises(SweepError, match="no longer resolve to the stored ids"):
        ledger.specs_from_manifest(manifest)
    with pytest.raises(SweepError, match="manifest's specs cannot be read"):
        ledger.specs_from_manifest({"name": "exp", "cells": []})


def test_a_broken_manifest_is_an_error_not_a_missing_grid(tmp_path):
    (tmp_path / store.MANIFEST).write_text("{not json")
    with pytest.raises(SchemaError, match="not valid JSON"):
        store.read_manifest(tmp_path)
    (tmp_path / store.MANIFEST).write_text(json.dumps({"cell_ids": ["a"]}))
    with pytest.raises(SchemaError, match="list of cell ids under 'cells'"):
        ledger.read_sweep(tmp_path.parent, tmp_path.name)


def test_status_counts_a_later_success_over_an_old_failure(tmp_path, smoke_specs):
    sweep_dir = tmp_path / "exp"
    sweep_dir.mkdir()
    store.write_manifest(sweep_dir, ledger.new_manifest("exp", "smoke", smoke_specs))
    first, second = smoke_specs[:2]
    for spec in (first, second):
        store.record_failure(sweep_dir, spec.cell_id, spec.domain, spec.method, "Traceback\nRuntimeError: boom")
    # A failure record left by an earlier attempt of a cell that then finished.
    store.write_row(sweep_dir, finished_row(first), sweep_id="exp")
    done, failed = ledger.finished_and_failed(sweep_dir, [s.cell_id for s in smoke_specs])
    assert done == {first.cell_id} and failed == {second.cell_id}
    text = ledger.sweep_status("exp", tmp_path)
    assert text.splitlines()[-3].split() == ["total", "1", "1", "16"]
    assert text.splitlines()[-1] == f"  1 cell: RuntimeError: boom (first: {second.cell_id})"
    listed = ledger.sweep_status("exp", tmp_path, list_failed=True)
    assert listed.splitlines()[-1] == f"failed {second.cell_id}: RuntimeError: boom"


def test_status_groups_failures_by_cause(tmp_path, smoke_specs):
    """A base that met no bar is its trial's cause (every cell of the trial), other errors are grouped by
    their last line with the numbers set aside; the causes with the most cells first."""
    sweep_dir = tmp_path / "exp"
    sweep_dir.mkdir()
    store.write_manifest(sweep_dir, ledger.new_manifest("exp", "smoke", smoke_specs))
    by_trial = {}
    for s in smoke_specs:
        by_trial.setdefault(s.trial, []).append(s)
    (t0, cells0), (t1, cells1) = sorted(by_trial.items())
    for s in cells0:
        store.record_failure(sweep_dir, s.cell_id, s.domain, s.method,
                             f"Traceback\nBaseRejected: {s.domain} base for trial {s.trial}: no attempt of 10 reached "
                             f"the bar (scores [1.0, 2.0])")
    for k, s in enumerate(cells1[:3]):
        store.record_failure(sweep_dir, s.cell_id, s.domain, s.method, f"RuntimeError: non-finite loss at update {k + 7}")
    store.record_failure(sweep_dir, cells1[3].cell_id, cells1[3].domain, cells1[3].method, "ValueError: odd")
    lines = ledger.sweep_status("exp", tmp_path).splitlines()
    attempts = cells0[0].resolved().base_max_attempts
    first = min(s.cell_id for s in cells1[:3])
    assert lines[-4:] == [
        f"failed: {len(cells0) + 4} cells, 3 causes (asp-dist status exp --failed lists each cell)",
        f"  1 signaling trial found no base in {attempts} attempts: {t0} — {len(cells0)} cells",
        f"  3 cells: {store.last_error_line(store.failed_cells(sweep_dir)[first])} (first: {first})",
        f"  1 cell: ValueError: odd (first: {cells1[3].cell_id})",
    ]
    assert sum(line.startswith("failed ") for line in ledger.sweep_status("exp", tmp_path, list_failed=True)
               .splitlines()) == len(cells0) + 4


def test_status_and_refused_inputs_never_import_ray(tmp_path, smoke_specs):
    sweep_dir = tmp_path / "exp"
    sweep_dir.mkdir()
    store.write_manifest(sweep_dir, ledger.new_manifest("exp", "smoke", smoke_specs))
    code = ("import sys\n"
            "from asp_dist.cli import main\n"
            f"assert main(['status', 'exp', '--results', {str(tmp_path)!r}]) == 0\n"
            f"assert main(['sweep', 'smoke', '--name', '../x', '--results', {str(tmp_path)!r}]) == 2\n"
            f"assert main(['resume', 'ghost', '--results', {str(tmp_path)!r}]) == 2\n"
            "assert 'ray' not in sys.modules, 'ray was imported'\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.splitlines()[-1].split() == ["total", "0", "0", "18"]



@pytest.mark.parametrize("command", ["sweep", "resume"])
def test_a_run_reads_its_manifest_once_before_its_lock_and_once_under_it(tmp_path, smoke_specs, monkeypatch, command,
                                                                         capsys):
    """The plan carries the manifest its checks read (asp_dist.sweep.plan.Plan.manifest); the run reads it again
    only under the sweep's lock, where another run may have changed it. A finished sweep run again trains nothing
    and starts no Ray, so the count is the driver's whole."""
    from asp_dist.cli import main

    sweep_dir = tmp_path / "smoke"
    store.write_manifest(sweep_dir, ledger.new_manifest("smoke", "smoke", smoke_specs))
    for spec in smoke_specs:
        store.write_row(sweep_dir, finished_row(spec), sweep_id="smoke")
    reads = []
    read = store.read_manifest
    monkeypatch.setattr(store, "read_manifest", lambda d: reads.append(d) or read(d))
    argv = ["sweep", "smoke"] if command == "sweep" else ["resume", "smoke"]
    assert main([*argv, "--results", str(tmp_path)]) == 0, capsys.readouterr().err
    # resume of a finished sweep stops after its checks (nothing to resume): one read
    assert len(reads) == (2 if command == "sweep" else 1), reads
