"""The sweep service: a grid of cells on Ray Tune, one trial per cell, results in Parquet.

This is the only module that imports Ray. Flow of ``run_sweep``:

1. validate everything a user can get wrong (space, name, results dir, grid vs. manifest, lock)
   before anything is written;
2. take the sweep's lock (``results/<sweep>/.lock``, fcntl: released by the OS even after SIGKILL);
3. drop the cells that already have a Parquet file (the record that a cell is done);
4. start an embedded Ray (or join ``--address``) and run one Tune trial per remaining cell,
   1 CPU each, ``reuse_actors=True``, at most ``workers`` at once. If the previous run of this
   sweep was interrupted, its Tune experiment is restored (``Tuner.restore``) so running cells
   continue from their last checkpoint (``tune.get_checkpoint``);
5. each trial gets its base from the shared cache, runs ``run_cell`` (checkpointing through
   ``tune.report(..., checkpoint=...)``) and writes its row through ``asp_dist.results.store``.

A worker that dies is retried ``max_failures`` times from its last checkpoint; a cell that
still fails (or fails deterministically, e.g. a base that never meets its bar) is recorded
under ``failed/`` and the sweep goes on. ``resume`` retries failed cells.
"""

from __future__ import annotations

import fcntl
import getpass
import json
import logging
import os
import signal
import socket
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator, TextIO

# Before Ray is imported: no usage stats, no Tune CSV/JSON/TensorBoard loggers per trial.
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("TUNE_DISABLE_AUTO_CALLBACK_LOGGERS", "1")
os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")

import ray  # noqa: E402
import torch  # noqa: E402
from ray import tune  # noqa: E402

from asp_dist import __version__
from asp_dist.errors import SweepError
from asp_dist.fsutil import atomic_write  # noqa: E402
from asp_dist.results import store  # noqa: E402
from asp_dist.spec import CellSpec, SpecError  # noqa: E402
from asp_dist.sweep.base_cache import get_base  # noqa: E402
from asp_dist.sweep.progress import SweepProgress  # noqa: E402
from asp_dist.sweep.spaces import expand, grid_hash, space_file  # noqa: E402
from asp_dist.training.bases import BaseRejected  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402

__all__ = ["SweepError", "run_sweep", "resume_sweep", "sweep_status", "SweepResult"]

OBJECT_STORE_BYTES = 100 * 1024**2  # cells exchange no large objects; Ray's minimum is ~75 MB
DEFAULT_MAX_FAILURES = 2
DEFAULT_CHECKPOINT_EVERY_S = 30.0
LOCK_FILE = ".lock"
TUNE_DIR = "tune"
TUNE_CURRENT = "current.json"  # which Tune experiment covers which cells
# Test hook, comma-separated "<cell_id substring>:<train step>:<marker file | always | raise>":
# SIGKILLs the worker running a matching cell once (the marker records that it happened) or
# every time, or raises a deterministic failure (BaseRejected) in it.
FAULT_ENV = "ASP_DIST_FAULT_KILL_WORKER"

log = logging.getLogger(__name__)


@dataclass
class SweepResult:
    name: str
    sweep_dir: Path
    total: int
    done: int
    failed: int

    @property
    def pending(self) -> int:
        return self.total - self.done - self.failed


# ---- the Tune trial: one cell ---------------------------------------------------------------------
def train_cell(config: dict[str, Any]) -> None:
    """Function trainable. Must keep no state between calls: actors are reused across cells."""
    torch.set_num_threads(1)
    config = config["cell"]
    spec = CellSpec.from_dict(config["spec"])
    sweep_dir = Path(config["sweep_dir"])
    cell_id = config["cell_id"]
    if store.is_done(sweep_dir, spec.domain, spec.method, cell_id):
        tune.report({"cell_done": 1, "skipped": 1})  # finished before Tune's state caught up
        return
    restore = None
    checkpoint = tune.get_checkpoint()
    if checkpoint is not None:
        with checkpoint.as_directory() as d:
            restore = torch.load(Path(d) / "state.pt", weights_only=False)

    def save(state: dict) -> None:
        with tempfile.TemporaryDirectory(prefix="asp-ckpt-") as d:
            torch.save(state, Path(d) / "state.pt")
            # Persisted to the trial's storage before report() returns.
            tune.report({"cell_done": 0, "step": state["trainer"]["step"]},
                        checkpoint=tune.Checkpoint.from_directory(d))

    try:
        base, _ = get_base(spec, sweep_dir / "bases")
        row = run_cell(spec, base=base, progress=_fault_injector(cell_id), checkpoint=save, restore=restore,
                       checkpoint_every_s=config["checkpoint_every_s"])
    except (SpecError, BaseRejected) as e:
        # Deterministic: a retry would fail the same way. Record and let the sweep go on.
        store.record_failure(sweep_dir, cell_id, spec.domain, spec.method, f"{type(e).__name__}: {e}")
        tune.report({"cell_done": 0, "cell_failed": 1})
        return
    row["ray_node_id"] = ray.get_runtime_context().get_node_id()
    row["ray_version"] = ray.__version__
    store.write_row(sweep_dir, row, config["sweep_id"])
    store.clear_failure(sweep_dir, cell_id)
    tune.report({"cell_done": 1, "eval_mixed": float(row["eval_mixed"])})


def _fault_injector(cell_id: str):
    """Test hook (see FAULT_ENV): a progress callback that SIGKILLs this worker process."""
    for entry in filter(None, os.environ.get(FAULT_ENV, "").split(",")):
        match, step, marker = entry.split(":", 2)
        if match in cell_id:
            break
    else:
        return None

    def progress(phase: str, done: int, total: int, info: dict) -> None:
        if phase == "train" and done >= int(step) and marker == "raise":
            raise BaseRejected(f"injected deterministic failure of {cell_id}")
        if phase == "train" and done >= int(step) and (marker == "always" or not os.path.exists(marker)):
            if marker != "always":
                Path(marker).write_text(f"killed {cell_id} at step {done}\n")
            os.kill(os.getpid(), signal.SIGKILL)

    return progress


def trial_name(trial) -> str:
    return trial.config["cell"]["cell_id"]


# ---- driver side: progress and failures ----------------------------------------------------------
_ACTIVE: dict[str, Any] = {}  # the live progress display of this driver (callbacks are pickled by Tune)


class SweepCallback(tune.Callback):
    """Feeds the terminal progress and records cells that failed after every retry."""

    def __init__(self, sweep_dir: str):
        self.sweep_dir = sweep_dir

    def __reduce__(self):  # Tune pickles its callbacks with the experiment; keep only the path
        return (SweepCallback, (self.sweep_dir,))

    def _refresh(self, trials, force: bool = False) -> None:
        progress: SweepProgress | None = _ACTIVE.get("progress")
        if progress is None:
            return
        grid = _ACTIVE["cell_ids"]
        done_ids = store.done_cell_ids(Path(self.sweep_dir)) & grid
        failed = (set(store.failed_cells(Path(self.sweep_dir))) & grid) - done_ids
        running = sum(1 for t in trials if t.status == "RUNNING")
        progress.update(done=len(done_ids), failed=len(failed), running=running, force=force)

    def on_step_end(self, iteration, trials, **info):
        progress = _ACTIVE.get("progress")
        if progress is not None:
            progress.update(running=sum(1 for t in trials if t.status == "RUNNING"))

    def on_trial_start(self, iteration, trials, trial, **info):
        self._refresh(trials)

    def on_trial_complete(self, iteration, trials, trial, **info):
        self._refresh(trials)

    def on_trial_error(self, iteration, trials, trial, **info):
        error = "worker failed"
        if trial.error_file and os.path.exists(trial.error_file):
            error = Path(trial.error_file).read_text()
        cell = trial.config["cell"]
        spec = cell["spec"]
        store.record_failure(Path(self.sweep_dir), cell["cell_id"], spec["domain"], spec["method"],
                             f"failed after {trial.num_failures} attempt(s): {error}")
        self._refresh(trials)


# ---- validation, lock, manifest -----------------------------------------------------------------
def sweep_dir_for(results: str | Path, name: str) -> Path:
    if not store.SWEEP_NAME_RE.match(name):
        raise SweepError(f"invalid sweep name {name!r}: use letters, digits, '.', '_' or '-' (at most 64)")
    return Path(results).expanduser().resolve() / name


def check_writable(sweep_dir: Path) -> None:
    try:
        sweep_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=sweep_dir, prefix=".write-test-"):
            pass
    except OSError as e:
        raise SweepError(f"results dir {sweep_dir.parent} is not writable ({e.strerror or e}); "
                         f"choose another with --results") from None


@contextmanager
def sweep_lock(sweep_dir: Path) -> Iterator[None]:
    """Refuse a second concurrent sweep on one name. The OS drops the lock when the holder dies."""
    path = sweep_dir / LOCK_FILE
    fh = open(path, "a+")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            raise SweepError(f"sweep {sweep_dir.name!r} is already running ({holder}); wait for it to finish "
                             f"or use another --name") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()} since "
                 f"{datetime.now(timezone.utc).isoformat(timespec='seconds')}")
        fh.flush()
        yield
    finally:
        fh.close()


def lock_holder(sweep_dir: Path) -> str | None:
    """Who holds the sweep's lock, or None if no sweep is running on it."""
    path = sweep_dir / LOCK_FILE
    if not path.exists():
        return None
    with open(path, "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            return fh.read().strip() or "unknown"
        fcntl.flock(fh, fcntl.LOCK_UN)
    return None


def check_manifest(sweep_dir: Path, name: str, specs: list[CellSpec], space: str) -> dict[str, Any]:
    """The sweep's manifest; refuses a grid that differs from the one stored under this name."""
    digest = grid_hash(specs)
    existing = store.read_manifest(sweep_dir)
    if existing is not None:
        if existing["grid_hash"] != digest:
            raise SweepError(f"sweep {name!r} in {sweep_dir.parent} was started with another grid (space "
                             f"{existing.get('space')!r}, {len(existing['cells'])} cells, hash {existing['grid_hash']}; "
                             f"now {space!r}, {len(specs)} cells, hash {digest}); use another --name")
        return existing
    return {"name": name, "space": space, "grid_hash": digest, "cells": [s.cell_id for s in specs],
            "specs": [s.to_dict() for s in specs], "asp_dist_version": __version__,
            "created_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def specs_from_manifest(manifest: dict[str, Any]) -> list[CellSpec]:
    specs = [CellSpec.from_dict(d).resolved() for d in manifest["specs"]]
    if [s.cell_id for s in specs] != manifest["cells"]:
        raise SweepError(f"sweep {manifest['name']!r}: its cells no longer resolve to the stored ids "
                         f"(CellSpec or domain defaults changed); start a new sweep name")
    return specs


# ---- Ray ----------------------------------------------------------------------------------------
def default_ray_temp_dir() -> str:
    """Short (Unix sockets live under it, ~107-char limit) and per user, never a bare /tmp/ray."""
    return f"/tmp/asp-ray-{getpass.getuser()}"


@contextmanager
def ray_session(workers: int, address: str | None, temp_dir: str | None) -> Iterator[None]:
    if ray.is_initialized():
        raise SweepError("Ray is already initialised in this process; run the sweep in a fresh process")
    common = dict(log_to_driver=False, logging_level=logging.WARNING, configure_logging=True)
    try:
        if address:
            ray.init(address=address, **common)
        else:
            os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # local-only default: nothing listens outside
            ray.init(address="local", num_cpus=workers, _temp_dir=temp_dir or default_ray_temp_dir(),
                     include_dashboard=False, object_store_memory=OBJECT_STORE_BYTES, **common)
    except ConnectionError as e:
        raise SweepError(f"cannot connect to the Ray cluster at {address}: {e}") from None
    try:
        yield
    finally:
        ray.shutdown()


def _tune_experiment(sweep_dir: Path, pending: list[CellSpec], allow_restore: bool = True) -> tuple[str, bool]:
    """Name of the Tune experiment to run, and whether to restore it.

    An interrupted experiment is restored when it covers every pending cell (then its running
    trials continue from their checkpoints); otherwise a new experiment over just the pending
    cells starts (e.g. after a clean finish with failures, or when the state is unreadable).
    """
    tune_root = sweep_dir / TUNE_DIR
    current_path = tune_root / TUNE_CURRENT
    pending_ids = {s.cell_id for s in pending}
    if current_path.exists():
        current = json.loads(current_path.read_text())
        exp_path = tune_root / current["experiment"]
        if allow_restore and pending_ids <= set(current["cells"]) and tune.Tuner.can_restore(str(exp_path)):
            return current["experiment"], True
        number = int(current["experiment"].rsplit("-", 1)[1]) + 1
    else:
        number = 1
    experiment = f"run-{number}"
    atomic_write(current_path, json.dumps({"experiment": experiment, "cells": sorted(pending_ids)}))
    return experiment, False


def _run_tune(sweep_dir: Path, name: str, pending: list[CellSpec], workers: int, max_failures: int,
              checkpoint_every_s: float) -> None:
    # Rows live in Parquet, not in Tune's per-trial logs (disabled above): silence Tune's
    # complaint that it cannot build its own result table from them.
    logging.getLogger("ray.tune.analysis.experiment_analysis").setLevel(logging.ERROR)
    experiment, restore = _tune_experiment(sweep_dir, pending)
    if restore:
        try:
            _tuner(sweep_dir, name, experiment, True, pending, workers, max_failures, checkpoint_every_s).fit()
        except Exception as e:  # noqa: BLE001 - an unreadable Tune state must not block the sweep
            log.warning("could not restore Tune experiment %s (%s); starting a new one", experiment, e)
        # Tune does not rerun trials it saw finish, e.g. a cell that failed deterministically
        # (recorded under failed/): whatever is still missing runs in a fresh experiment.
        pending = [s for s in pending if not store.is_done(sweep_dir, s.domain, s.method, s.cell_id)]
        if not pending:
            return
        experiment, _ = _tune_experiment(sweep_dir, pending, allow_restore=False)
    _tuner(sweep_dir, name, experiment, False, pending, workers, max_failures, checkpoint_every_s).fit()


def _tuner(sweep_dir: Path, name: str, experiment: str, restore: bool, pending: list[CellSpec], workers: int,
           max_failures: int, checkpoint_every_s: float) -> tune.Tuner:
    trainable = tune.with_resources(train_cell, {"cpu": 1})
    storage = sweep_dir / TUNE_DIR
    if restore:
        # Restores the stored Tune settings too (max_failures, checkpoint interval of the cells).
        return tune.Tuner.restore(str(storage / experiment), trainable=trainable,
                                  resume_unfinished=True, resume_errored=True)
    configs = [{"spec": s.to_dict(), "cell_id": s.cell_id, "sweep_dir": str(sweep_dir), "sweep_id": name,
                "checkpoint_every_s": checkpoint_every_s} for s in pending]
    return tune.Tuner(
        trainable,
        param_space={"cell": tune.grid_search(configs)},
        tune_config=tune.TuneConfig(max_concurrent_trials=workers, reuse_actors=True,
                                    trial_name_creator=trial_name, trial_dirname_creator=trial_name),
        run_config=tune.RunConfig(
            name=experiment, storage_path=str(storage), verbose=0,
            failure_config=tune.FailureConfig(max_failures=max_failures),
            # num_to_keep=1 also makes Tune save its experiment state after every trial
            # checkpoint, so a killed driver resumes each cell from its latest checkpoint.
            checkpoint_config=tune.CheckpointConfig(num_to_keep=1),
            callbacks=[SweepCallback(str(sweep_dir))],
        ),
    )


# ---- public entry points ------------------------------------------------------------------------
def run_sweep(space: str, *, name: str | None = None, results: str | Path = "results", workers: int = 2,
              address: str | None = None, max_failures: int = DEFAULT_MAX_FAILURES,
              checkpoint_every_s: float = DEFAULT_CHECKPOINT_EVERY_S, ray_temp_dir: str | None = None,
              stream: TextIO | None = None) -> SweepResult:
    """Run (or continue) the sweep ``name`` over ``space``; see the module docstring."""
    if workers < 1:
        raise SweepError(f"--workers must be >= 1, got {workers}")
    if max_failures < 0:
        raise SweepError(f"--max-failures must be >= 0, got {max_failures}")
    specs = expand(space)
    space_name = space_file(space).stem
    return _run(specs, space_name, name or space_name, results, workers, address, max_failures,
                checkpoint_every_s, ray_temp_dir, stream)


def resume_sweep(name: str, *, results: str | Path = "results", workers: int = 2, address: str | None = None,
                 max_failures: int = DEFAULT_MAX_FAILURES, checkpoint_every_s: float = DEFAULT_CHECKPOINT_EVERY_S,
                 ray_temp_dir: str | None = None, stream: TextIO | None = None) -> SweepResult:
    """Continue a sweep from its manifest (no space file needed)."""
    sweep_dir = sweep_dir_for(results, name)
    manifest = store.read_manifest(sweep_dir)
    if manifest is None:
        raise SweepError(f"no sweep {name!r} under {sweep_dir.parent}; start it with `asp-dist sweep SPACE --name {name}`")
    specs = specs_from_manifest(manifest)
    return _run(specs, manifest["space"], name, results, workers, address, max_failures,
                checkpoint_every_s, ray_temp_dir, stream)


def _run(specs: list[CellSpec], space: str, name: str, results: str | Path, workers: int, address: str | None,
         max_failures: int, checkpoint_every_s: float, ray_temp_dir: str | None,
         stream: TextIO | None) -> SweepResult:
    sweep_dir = sweep_dir_for(results, name)
    if sweep_dir.exists() and store.read_manifest(sweep_dir) is None and any(sweep_dir.iterdir()):
        raise SweepError(f"{sweep_dir} exists and is not a sweep (no manifest.json); choose another --name")
    check_writable(sweep_dir)
    stream = stream or sys.stderr
    with sweep_lock(sweep_dir):
        if store.read_manifest(sweep_dir) is None:
            store.write_manifest(sweep_dir, check_manifest(sweep_dir, name, specs, space))
        else:
            check_manifest(sweep_dir, name, specs, space)  # refuses a different grid
        grid_ids = {s.cell_id for s in specs}
        done = store.done_cell_ids(sweep_dir) & grid_ids
        pending = [s for s in specs if s.cell_id not in done]
        progress = SweepProgress(name, total=len(specs), already_done=len(done), stream=stream)
        where = f"cluster {address}" if address else f"embedded Ray, {workers} worker(s)"
        stream.write(f"sweep {name}: space {space}, {len(specs)} cells ({len(done)} already done), "
                     f"{where}, results in {sweep_dir}\n")
        if pending:
            _ACTIVE.update(progress=progress, cell_ids=grid_ids)
            try:
                with ray_session(workers, address, ray_temp_dir):
                    _run_tune(sweep_dir, name, pending, workers, max_failures, checkpoint_every_s)
            finally:
                _ACTIVE.clear()
        done = store.done_cell_ids(sweep_dir) & grid_ids
        failed = (set(store.failed_cells(sweep_dir)) & grid_ids) - done
        progress.update(done=len(done), failed=len(failed), running=0)
        progress.finish()
        return SweepResult(name, sweep_dir, len(specs), len(done), len(failed))


def sweep_status(name: str, results: str | Path = "results") -> str:
    """Done / failed / pending counts per domain and method, as a printable table."""
    sweep_dir = sweep_dir_for(results, name)
    manifest = store.read_manifest(sweep_dir)
    if manifest is None:
        raise SweepError(f"no sweep {name!r} under {sweep_dir.parent}")
    done = store.done_cell_ids(sweep_dir)
    failed = store.failed_cells(sweep_dir)
    table: dict[tuple[str, str], list[int]] = {}
    for cell_id, spec in zip(manifest["cells"], manifest["specs"]):
        counts = table.setdefault((spec["domain"], spec["method"]), [0, 0, 0])
        if cell_id in done:
            counts[0] += 1
        elif cell_id in failed:
            counts[1] += 1
        else:
            counts[2] += 1
    holder = lock_holder(sweep_dir)
    lines = [f"sweep {name}: space {manifest['space']}, {len(manifest['cells'])} cells, grid {manifest['grid_hash']}, "
             + (f"RUNNING ({holder})" if holder else "not running"),
             f"{'domain':<12}{'method':<8}{'done':>7}{'failed':>8}{'pending':>9}"]
    totals = [0, 0, 0]
    for (domain, method), (d, f, p) in sorted(table.items()):
        lines.append(f"{domain:<12}{method:<8}{d:>7}{f:>8}{p:>9}")
        totals = [totals[0] + d, totals[1] + f, totals[2] + p]
    lines.append(f"{'total':<20}{totals[0]:>7}{totals[1]:>8}{totals[2]:>9}")
    for cell_id, info in sorted(failed.items()):
        if cell_id not in done and cell_id in set(manifest["cells"]):
            first_line = info["error"].strip().splitlines()[-1] if info["error"].strip() else ""
            lines.append(f"failed {cell_id}: {first_line[:160]}")
    return "\n".join(lines)
