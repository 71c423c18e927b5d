"""The sweep service on Ray Tune: one trial per cell, results in the store. The only Ray module.

Flow of ``run_sweep`` / ``resume_sweep``:

1. validate everything a user can get wrong (space, name, results dir, grid vs. manifest, lock)
   before anything is written (asp_dist.sweep.ledger, no Ray);
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

import getpass
import json
import logging
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, TextIO

# Before Ray is imported: no usage stats, no Tune CSV/JSON/TensorBoard loggers per trial.
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("TUNE_DISABLE_AUTO_CALLBACK_LOGGERS", "1")
os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")

import ray  # noqa: E402
import torch  # noqa: E402
from ray import tune  # noqa: E402

from asp_dist.errors import SpecError, SweepError  # noqa: E402
from asp_dist.fsutil import atomic_write  # noqa: E402
from asp_dist.results import store  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.sweep import ledger  # noqa: E402
from asp_dist.sweep.base_cache import get_base  # noqa: E402
from asp_dist.sweep.ledger import SweepResult  # noqa: E402
from asp_dist.sweep.progress import SweepCounter  # noqa: E402
from asp_dist.sweep.spaces import expand, space_file  # noqa: E402
from asp_dist.training.bases import BaseRejected  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402

__all__ = ["run_sweep", "resume_sweep", "SweepResult", "train_cell"]

OBJECT_STORE_BYTES = 100 * 1024**2  # cells exchange no large objects; Ray's minimum is ~75 MB
DEFAULT_MAX_FAILURES = 2
DEFAULT_CHECKPOINT_EVERY_S = 30.0
TUNE_DIR = "tune"
TUNE_CURRENT = "current.json"  # which Tune experiment covers which cells

log = logging.getLogger(__name__)


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
        base, _ = get_base(spec, store.bases_dir(sweep_dir))
        curve: list[dict[str, float]] = []
        row = run_cell(spec, base=base, checkpoint=save, restore=restore,
                       checkpoint_every_s=config["checkpoint_every_s"], curve=curve)
    except (SpecError, BaseRejected) as e:
        # Deterministic: a retry would fail the same way. Record and let the sweep go on.
        store.record_failure(sweep_dir, cell_id, spec.domain, spec.method, f"{type(e).__name__}: {e}")
        tune.report({"cell_done": 0, "cell_failed": 1})
        return
    row["ray_node_id"] = ray.get_runtime_context().get_node_id()
    row["ray_version"] = ray.__version__
    store.write_curve(sweep_dir, row, curve)
    store.write_row(sweep_dir, row, config["sweep_id"])
    store.clear_failure(sweep_dir, cell_id)
    tune.report({"cell_done": 1, "eval_mixed": float(row["eval_mixed"])})


def trial_name(trial) -> str:
    """A trial's name and directory are its cell id (a worker's working directory ends with it)."""
    return trial.config["cell"]["cell_id"]


# ---- driver side: counts and failures ------------------------------------------------------------
class SweepCallback(tune.Callback):
    """Feeds the sweep's progress view and records cells that failed after every retry.

    Tune pickles its callbacks with the experiment and a restored experiment brings back the
    pickled ones; only the path and the grid are pickled, and a restored callback starts its own
    view on stderr."""

    def __init__(self, sweep_dir: str, name: str, grid: dict[str, str], counter: SweepCounter | None = None):
        self.sweep_dir, self.name, self.grid = sweep_dir, name, grid  # grid: cell id -> "domain/method"
        self.counter = counter

    def __reduce__(self):
        return (SweepCallback, (self.sweep_dir, self.name, self.grid))

    def _counter(self) -> SweepCounter:
        if self.counter is None:
            done, _ = ledger.finished_and_failed(Path(self.sweep_dir), self.grid)
            self.counter = SweepCounter(self.name, self.grid, done, where=self.sweep_dir)
        return self.counter

    @staticmethod
    def _running(trials) -> set[str]:
        return {t.config["cell"]["cell_id"] for t in trials if t.status == "RUNNING"}

    def _refresh(self, trials) -> None:
        done, failed = ledger.finished_and_failed(Path(self.sweep_dir), self.grid)
        self._counter().update(done=done, failed=failed, running=self._running(trials),
                               last_failure=last_failure(Path(self.sweep_dir), failed))

    def on_step_end(self, iteration, trials, **info):
        self._counter().update(running=self._running(trials))

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


def last_failure(sweep_dir: Path, failed: set[str]) -> str:
    """The newest failure of the grid, as "cell id: last line of its error"."""
    records = [r for cell_id, r in store.failed_cells(sweep_dir).items() if cell_id in failed]
    if not records:
        return ""
    newest = max(records, key=lambda r: str(r.get("failed_at", "")))
    return f"{newest['cell_id']}: {store.last_error_line(newest)}"


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


def _run_tune(sweep_dir: Path, callback: SweepCallback, pending: list[CellSpec], workers: int, max_failures: int,
              checkpoint_every_s: float) -> None:
    # Rows live in Parquet, not in Tune's per-trial logs (disabled above): silence Tune's
    # complaint that it cannot build its own result table from them.
    logging.getLogger("ray.tune.analysis.experiment_analysis").setLevel(logging.ERROR)
    experiment, restore = _tune_experiment(sweep_dir, pending)
    if restore:
        try:
            _restored_tuner(sweep_dir, experiment).fit()
        except Exception as e:  # noqa: BLE001 - an unreadable Tune state must not block the sweep
            log.warning("could not restore Tune experiment %s (%s); starting a new one", experiment, e)
        # Tune does not rerun trials it saw finish, e.g. a cell that failed deterministically
        # (recorded under failed/): whatever is still missing runs in a fresh experiment.
        pending = [s for s in pending if not store.is_done(sweep_dir, s.domain, s.method, s.cell_id)]
        if not pending:
            return
        experiment, _ = _tune_experiment(sweep_dir, pending, allow_restore=False)
    _new_tuner(sweep_dir, callback, experiment, pending, workers, max_failures, checkpoint_every_s).fit()


def _trainable():
    return tune.with_resources(train_cell, {"cpu": 1})


def _restored_tuner(sweep_dir: Path, experiment: str) -> tune.Tuner:
    # Restores the stored Tune settings too (max_failures, checkpoint interval, callbacks).
    return tune.Tuner.restore(str(sweep_dir / TUNE_DIR / experiment), trainable=_trainable(),
                              resume_unfinished=True, resume_errored=True)


def _new_tuner(sweep_dir: Path, callback: SweepCallback, experiment: str, pending: list[CellSpec], workers: int,
               max_failures: int, checkpoint_every_s: float) -> tune.Tuner:
    configs = [{"spec": s.to_dict(), "cell_id": s.cell_id, "sweep_dir": str(sweep_dir), "sweep_id": callback.name,
                "checkpoint_every_s": checkpoint_every_s} for s in pending]
    return tune.Tuner(
        _trainable(),
        param_space={"cell": tune.grid_search(configs)},
        tune_config=tune.TuneConfig(max_concurrent_trials=workers, reuse_actors=True,
                                    trial_name_creator=trial_name, trial_dirname_creator=trial_name),
        run_config=tune.RunConfig(
            name=experiment, storage_path=str(sweep_dir / TUNE_DIR), verbose=0,
            failure_config=tune.FailureConfig(max_failures=max_failures),
            # num_to_keep=1 also makes Tune save its experiment state after every trial
            # checkpoint, so a killed driver resumes each cell from its latest checkpoint.
            checkpoint_config=tune.CheckpointConfig(num_to_keep=1),
            callbacks=[callback],
        ),
    )


# ---- public entry points ------------------------------------------------------------------------
def run_sweep(space: str, *, name: str | None = None, results: str | Path = store.DEFAULT_RESULTS, workers: int = 2,
              address: str | None = None, max_failures: int = DEFAULT_MAX_FAILURES,
              checkpoint_every_s: float = DEFAULT_CHECKPOINT_EVERY_S, ray_temp_dir: str | None = None,
              stream: TextIO | None = None) -> SweepResult:
    """Run (or continue) the sweep ``name`` over ``space``; see the module docstring."""
    ledger.check_run_options(workers, max_failures, checkpoint_every_s)
    specs = expand(space)
    space_name = space_file(space).stem
    return _run(specs, space_name, name or space_name, results, workers, address, max_failures,
                checkpoint_every_s, ray_temp_dir, stream)


def resume_sweep(name: str, *, results: str | Path = store.DEFAULT_RESULTS, workers: int = 2,
                 address: str | None = None, max_failures: int = DEFAULT_MAX_FAILURES,
                 checkpoint_every_s: float = DEFAULT_CHECKPOINT_EVERY_S, ray_temp_dir: str | None = None,
                 stream: TextIO | None = None) -> SweepResult:
    """Continue a sweep from its manifest (no space file needed)."""
    ledger.check_run_options(workers, max_failures, checkpoint_every_s)
    _, manifest = ledger.read_sweep(results, name)
    specs = ledger.specs_from_manifest(manifest)
    return _run(specs, manifest["space"], name, results, workers, address, max_failures,
                checkpoint_every_s, ray_temp_dir, stream)


def _run(specs: list[CellSpec], space: str, name: str, results: str | Path, workers: int, address: str | None,
         max_failures: int, checkpoint_every_s: float, ray_temp_dir: str | None,
         stream: TextIO | None) -> SweepResult:
    sweep_dir = ledger.sweep_dir_for(results, name)
    ledger.check_sweep_dir(sweep_dir)
    stream = stream or sys.stderr
    grid = {s.cell_id: f"{s.domain}/{s.method}" for s in specs}
    with ledger.sweep_lock(sweep_dir):
        manifest = ledger.check_manifest(sweep_dir, name, specs, space)  # refuses a different grid
        if store.read_manifest(sweep_dir) is None:
            store.write_manifest(sweep_dir, manifest)
        done, _ = ledger.finished_and_failed(sweep_dir, grid)
        pending = [s for s in specs if s.cell_id not in done]
        counter = SweepCounter(name, grid, done, stream=stream, where=str(store.cells_dir(sweep_dir)))
        where = f"cluster {address}" if address else f"embedded Ray, {workers} worker(s)"
        stream.write(f"sweep {name}: space {space}, {len(specs)} cells ({len(done)} already done), "
                     f"{where}, results in {sweep_dir}\n")
        if pending:
            callback = SweepCallback(str(sweep_dir), name, grid, counter)
            with ray_session(workers, address, ray_temp_dir):
                _run_tune(sweep_dir, callback, pending, workers, max_failures, checkpoint_every_s)
        done, failed = ledger.finished_and_failed(sweep_dir, grid)
        counter.update(done=done, failed=failed, running=set(), last_failure=last_failure(sweep_dir, failed))
        counter.finish()
        return SweepResult(name, sweep_dir, len(specs), len(done), len(failed))
