"""The sweep service on Ray Tune: one trial per cell, results in the store. The driver's side of Ray;
the sweep package's other Ray modules are trial.py (what a Tune trial runs), ray_host.py (the Ray it runs
on) and worker_start.py (what a worker skips at start). Nothing outside asp_dist.sweep imports Ray.

Flow of ``run_sweep`` / ``resume_sweep``:

1. validate everything a user can get wrong (space, name, results dir, grid vs. manifest, lock)
   before anything is written (asp_dist.sweep.ledger, no Ray);
2. take the sweep's lock (``results/<sweep>/.lock``, fcntl: released by the OS even after SIGKILL);
3. drop the cells that already have a Parquet file (the record that a cell is done);
4. start an embedded Ray (or join ``--address``: that connection is made, within
   ``--connect-timeout``, before anything is written) and run one Tune trial per remaining cell,
   1 CPU each, ``reuse_actors=True``, at most ``workers`` at once, in a new Tune experiment (run-<n>).
   Tune's own state is never restored (Tuner.restore unpickles it): a unit that an interrupted run left
   half-trained continues from the newest checkpoint it left there, read as plain tensors (trial.py);
5. each trial (asp_dist.sweep.trial) gets its bases from the shared cache, trains its unit through the one
   cell pipeline (checkpointing through ``tune.report(..., checkpoint=...)``) and writes its rows through
   ``asp_dist.results.store``.

With ``--pack trial|method`` (asp_dist.sweep.packing) a trial may instead train a *pack*: cells of one
domain trained as one batched model (asp_dist.training.engines). The packs are a function of the grid
and the packing stored in the manifest, so a resumed sweep rebuilds the same packs; a pack trains
whole and writes only its members without a row, each as a cell would (row, curve, failure).

A worker that dies is retried ``max_failures`` times from its last checkpoint; a cell that
still fails (or fails deterministically, e.g. a base that never meets its bar) is recorded
under ``failed/`` and the sweep goes on. ``resume`` retries failed cells.

With ``--results s3://bucket/prefix`` the same flow runs on object storage: cell rows, failures, the
manifest and the bases go to the bucket through the store, the lock is a lease (ledger), and Tune's
experiment state and checkpoints go to ``<sweep>/tune/`` in the bucket through
``RunConfig(storage_path=..., storage_filesystem=pyarrow S3FileSystem)``, seen through a filesystem that
skips rewriting unchanged files (asp_dist.sweep.tune_storage); a checkpoint is staged in the trial's working
directory under the Ray temp dir (node-local scratch) before Tune uploads it.

Nothing is left behind: checkpoints are staged under the sweep's own ``tune/.ckpt-tmp/``; SIGTERM
stops a sweep as Ctrl-C does (signals.sigterm_as_interrupt); a reaper process ends the embedded
Ray's processes within seconds when the driver dies, even by SIGKILL; and old session
directories of the embedded Ray are pruned at start.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import signal
import sys
import threading
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Iterator, TextIO

import ray
from ray import tune
from ray.tune.logger import CSVLoggerCallback, JsonLoggerCallback

from asp_dist.errors import DiskFull, StorageError, is_disk_full
from asp_dist.results import store
from asp_dist.results.location import AnyPath, as_path, write_replace
from asp_dist.results.s3 import S3Path
from asp_dist.sweep import ledger, preflight, provenance, signals, worker_start
from asp_dist.sweep.ledger import SweepResult
from asp_dist.sweep.packing import Unit, describe_units, make_units, resolve_packing, schedule
from asp_dist.sweep.plan import Plan, RunOptions
from asp_dist.sweep.progress import SweepCounter
from asp_dist.sweep.ray_host import _start_reaper, loopback_only, ray_session  # noqa: F401
from asp_dist.sweep.spaces import grid_hash
from asp_dist.sweep.trial import (  # noqa: F401  (train_cell, unit_config, trial_name: re-exported)
    CKPT_TMP,
    DISK_FULL,
    TUNE_DIR,
    config_cells,
    numbered_entries,
    train_cell,
    trial_name,
    unit_config,
    unit_from_config,
)
from asp_dist.sweep.tune_storage import tune_storage
from asp_dist.tracking.base import TrackingSettings

__all__ = ["run_sweep", "resume_sweep", "SweepResult", "train_cell"]

TUNE_CURRENT = "current.json"  # which Tune experiment covers which cells

log = logging.getLogger(__name__)


# ---- driver side: counts and failures ------------------------------------------------------------
class SweepCallback(tune.Callback):
    """Feeds the sweep's progress view and records cells that failed after every retry.

    Tune pickles its callbacks with its experiment state (asp-dist never restores one: each run is a new
    experiment); only the path and the grid are pickled."""

    def __init__(self, sweep_dir: str, name: str, grid: dict[str, str], counter: SweepCounter | None = None):
        self.sweep_dir, self.name, self.grid = sweep_dir, name, grid  # grid: cell id -> "domain/method"
        self.counter = counter

    def __reduce__(self):
        return (SweepCallback, (self.sweep_dir, self.name, self.grid))

    def _counter(self) -> SweepCounter:
        if self.counter is None:
            done, _ = ledger.finished_and_failed(as_path(self.sweep_dir), self.grid)
            self.counter = SweepCounter(self.name, self.grid, done, where=self.sweep_dir)
        return self.counter

    @staticmethod
    def _running(trials) -> set[str]:
        """The cells of the running trials (every member of a running pack: counts are per cell)."""
        return {cell_id for t in trials if t.status == "RUNNING" for cell_id, _, _ in config_cells(t.config["cell"])}

    def _refresh(self, trials) -> None:
        done, failed = ledger.finished_and_failed(as_path(self.sweep_dir), self.grid)
        self._counter().update(done=done, failed=failed, running=self._running(trials),
                               last_failure=last_failure(as_path(self.sweep_dir), failed))

    def on_trial_result(self, iteration, trials, trial, result, **info):
        if result.get(DISK_FULL) and not _DISK_FULL:
            _DISK_FULL.append(str(result[DISK_FULL]))

    def on_step_end(self, iteration, trials, **info):
        self._counter().update(running=self._running(trials))
        if _HUB:
            _HUB[0].poll()

    def on_trial_start(self, iteration, trials, trial, **info):
        self._refresh(trials)

    def on_trial_complete(self, iteration, trials, trial, **info):
        if unit_from_config(trial.config["cell"]).get("base_only"):
            self._counter().base_finished()
        self._refresh(trials)

    def on_trial_error(self, iteration, trials, trial, **info):
        error = "worker failed"
        if trial.error_file and os.path.exists(trial.error_file):
            error = Path(trial.error_file).read_text()
        config = unit_from_config(trial.config["cell"])
        if config.get("base_only"):  # its cells fail on the base when their units run
            self._counter().base_finished()
        where = f" (in pack {config['pack_id']})" if config["pack_id"] is not None else ""
        sweep_dir = as_path(self.sweep_dir)
        for cell_id, domain, method in config_cells(config):
            if not store.is_done(sweep_dir, domain, method, cell_id):
                store.record_failure(sweep_dir, cell_id, domain, method,
                                     f"failed after {trial.num_failures} attempt(s){where}: {error}")
        self._refresh(trials)


_DISK_FULL: list[str] = []  # this driver's: set by SweepCallback, read by DiskFullStopper and _run
_HUB: list["TrackerHub"] = []  # this driver's tracker hub, while one runs (the callback polls its warnings)


class TrackerHub:
    """The sweep's tracker hub (asp_dist.tracking.hub.Hub) as a Ray actor on this driver's node, named so that
    workers find it (hub_name); its warnings are printed here as they come (``poll``) and when it closes."""

    POLL_EVERY_S = 5.0

    def __init__(self, plan: Plan, settings: TrackingSettings, stream: TextIO):
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        from asp_dist.core.registry import get_domain
        from asp_dist.tracking.cells import describe_cells
        from asp_dist.tracking.hub import Hub, hub_name
        from asp_dist.training.row import code_revision

        cells = describe_cells(plan.specs, plan.name, code_revision(), lambda d: tuple(get_domain(d).metrics))
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
        self.actor = ray.remote(Hub).options(name=hub_name(plan.name), num_cpus=0, scheduling_strategy=here,
                                             max_concurrency=1).remote(settings, plan.name, cells)
        # Not waited for: Tune starts while the hub imports its trackers (workers' calls queue until it is up).
        self.stream, self.pending, self.polled = stream, self.actor.ready.remote(), time.monotonic()

    def _print(self, warnings: list[str]) -> None:
        for line in warnings:
            self.stream.write(line + "\n")

    def poll(self) -> None:
        """Print the hub's new warnings, never waiting for it (one request in flight at a time; Tune's loop
        calls this many times a second, the hub is asked every POLL_EVERY_S)."""
        if time.monotonic() - self.polled < 1.0:
            return
        if self.pending is not None:
            ready, _ = ray.wait([self.pending], timeout=0)
            if ready:
                self._print(ray.get(self.pending))
                self.pending = None
            self.polled = time.monotonic()
        elif time.monotonic() - self.polled >= self.POLL_EVERY_S:
            self.pending, self.polled = self.actor.take_warnings.remote(), time.monotonic()

    def close(self, interrupted: bool) -> None:
        """Wait for every point sent so far to be logged, then end the trackers' runs. The warnings of a poll still
        in flight are printed first: the hub gave them to that request, and answers its requests in order."""
        try:
            closing = self.actor.close.remote(interrupted)
            if self.pending is not None:
                self._print(ray.get(self.pending, timeout=120))
                self.pending = None
            self._print(ray.get(closing, timeout=120))
        except Exception as e:  # noqa: BLE001 - a hub that cannot close never fails the sweep
            self.stream.write(f"asp-dist: warning: the trackers did not close cleanly ({type(e).__name__}: {e})\n")
        ray.kill(self.actor)


@contextmanager
def _trackers(plan: Plan, settings: TrackingSettings, stream: TextIO) -> Iterator[None]:
    """The sweep's tracker hub while Tune runs (nothing without --logger)."""
    if not settings.loggers:
        yield
        return
    hub = TrackerHub(plan, settings, stream)
    _HUB.append(hub)
    interrupted = True
    try:
        yield
        interrupted = False
    finally:
        _HUB.clear()
        hub.close(interrupted)


class _DiskFullLogFilter(logging.Filter):
    """Tune logs a failed save of its experiment state with a traceback and goes on; on a full disk that
    is the sweep's to say, in one line: note it (the sweep stops) instead of printing it."""

    def filter(self, record: logging.LogRecord) -> bool:
        err = record.exc_info[1] if record.exc_info else None
        if err is not None and is_disk_full(err):
            if not _DISK_FULL:
                _DISK_FULL.append(getattr(err, "filename", None) or "")  # "": somewhere in the sweep
            return False
        return True


class DiskFullStopper(tune.Stopper):
    """Stops every trial once one found the disk full: the other cells would fail the same way. (State is
    this driver process's, _DISK_FULL, not the stopper's, which Tune pickles with its experiment state.)"""

    def __call__(self, trial_id, result) -> bool:
        return bool(result.get(DISK_FULL))

    def stop_all(self) -> bool:
        return bool(_DISK_FULL)


def last_failure(sweep_dir: AnyPath, failed: set[str]) -> str:
    """The newest failure of the grid, as "cell id: last line of its error"."""
    if not failed:  # the common case: no listing of failed/ (on S3 a request at every trial's start and end)
        return ""
    records = [r for cell_id, r in store.failed_cells(sweep_dir).items() if cell_id in failed]
    if not records:
        return ""
    newest = max(records, key=lambda r: str(r.get("failed_at", "")))
    return f"{newest['cell_id']}: {store.last_error_line(newest)}"


def _new_experiment(sweep_dir: AnyPath, pending: list[Unit]) -> str:
    """The name of a new Tune experiment for the pending units: run-<n>, n one above the sweep's last.

    A sweep never restores an earlier experiment (Tuner.restore unpickles Tune's state, and a results
    directory may be shared or copied: docs/decisions/0057-stored-artefacts-hold-no-code.md); each unit of
    the new one continues from the newest checkpoint its name left under an earlier one (asp_dist.sweep.trial),
    read as plain tensors. tune/current.json records which experiment covers which cells."""
    tune_root = sweep_dir / TUNE_DIR
    experiment = f"run-{max((n for n, _ in numbered_entries(tune_root, 'run-')), default=0) + 1}"
    cells = sorted(cell_id for unit in pending for cell_id in unit.cell_ids)
    write_replace(tune_root / TUNE_CURRENT, json.dumps({"experiment": experiment, "cells": cells}))
    return experiment


def _run_tune(sweep_dir: AnyPath, callback: SweepCallback, pending: list[Unit], workers: int, max_failures: int,
              checkpoint_every_s: float) -> None:
    # Rows live in Parquet, not in the results Tune keeps per trial (its JSON and CSV logs,
    # _tune_result_logs, are on for Tune's own use): silence its complaint that it cannot build its
    # result table from them.
    logging.getLogger("ray.tune.analysis.experiment_analysis").setLevel(logging.ERROR)
    state_log = logging.getLogger("ray.tune.execution.experiment_state")
    if not any(isinstance(f, _DiskFullLogFilter) for f in state_log.filters):
        state_log.addFilter(_DiskFullLogFilter())
    experiment = _new_experiment(sweep_dir, pending)
    _fit(_new_tuner(sweep_dir, callback, experiment, pending, workers, max_failures, checkpoint_every_s))


class _InterruptMark:
    """SIGINT handler while Tune runs, until Tune installs its own: Tune puts the previous handler back
    when (and only when) a SIGINT (or SIGTERM, signals.sigterm_as_interrupt) made it stop, so finding
    this mark back after fit() means that Tune stopped early, saved its state and returned."""

    asp_interrupt = True  # signals._sigterm: raise, do not call

    def __init__(self, previous):
        self.previous = previous

    def __call__(self, signum, frame):
        if callable(self.previous):
            return self.previous(signum, frame)
        if self.previous != signal.SIG_IGN:
            raise KeyboardInterrupt


@contextmanager
def _no_callback_tag_without_usage_stats() -> Iterator[None]:
    """Tune names the run's callbacks in a usage-stats tag (ray.air._internal.usage.tag_callbacks) by importing
    the MLflow, W&B, Comet and Aim integrations to compare classes (≈ 2.8 s of a sweep driver's CPU: mlflow is
    most of it), also when usage stats are off and the tag is never reported. Off is asp-dist's default
    (asp_dist/sweep/__init__.py); then the tag is skipped. With usage stats on, Ray records it as usual."""
    from ray._common.usage import usage_lib
    from ray.air._internal import usage as air_usage

    original = getattr(air_usage, "tag_callbacks", None)
    if original is None or usage_lib.usage_stats_enabled():
        yield
        return
    air_usage.tag_callbacks = lambda callbacks: False
    try:
        yield
    finally:
        air_usage.tag_callbacks = original


def _fit(tuner: tune.Tuner) -> None:
    """tuner.fit(), raising KeyboardInterrupt if Tune stopped early on a signal: Tune's own SIGINT
    handling returns normally, and the sweep must neither go on nor report a finished run."""
    if threading.current_thread() is not threading.main_thread() or os.environ.get("TUNE_DISABLE_SIGINT_HANDLER"):
        tuner.fit()
        return
    previous = signal.getsignal(signal.SIGINT)
    mark = _InterruptMark(previous)
    signal.signal(signal.SIGINT, mark)
    try:
        tuner.fit()
    finally:
        stopped_on_signal = signal.getsignal(signal.SIGINT) is mark
        signal.signal(signal.SIGINT, previous)  # also replaces a finished run's stale Tune handler
    if stopped_on_signal:
        raise KeyboardInterrupt


def _trainable():
    return tune.with_resources(train_cell, {"cpu": 1})


def _tune_result_logs() -> list:
    """Tune's JSON and CSV loggers, unless ASP_DIST_TUNE_RESULT_LOGS=0 (bench/bench_trackers.py measures them)."""
    if os.environ.get("ASP_DIST_TUNE_RESULT_LOGS", "1") == "0":
        return []
    return [JsonLoggerCallback(), CSVLoggerCallback()]


def _new_tuner(sweep_dir: AnyPath, callback: SweepCallback, experiment: str, pending: list[Unit], workers: int,
               max_failures: int, checkpoint_every_s: float) -> tune.Tuner:
    configs = [unit_config(u, sweep_dir, callback.name, checkpoint_every_s) for u in pending]
    storage_path, storage_fs = tune_storage(sweep_dir)
    return tune.Tuner(
        _trainable(),
        param_space={"cell": tune.grid_search(configs)},
        tune_config=tune.TuneConfig(max_concurrent_trials=workers, reuse_actors=True,
                                    trial_name_creator=trial_name, trial_dirname_creator=trial_name),
        run_config=tune.RunConfig(
            name=experiment, storage_path=storage_path, storage_filesystem=storage_fs, verbose=0,
            failure_config=tune.FailureConfig(max_failures=max_failures),
            # num_to_keep=1 also makes Tune save its experiment state after every trial
            # checkpoint, so a killed driver resumes each cell from its latest checkpoint.
            checkpoint_config=tune.CheckpointConfig(num_to_keep=1),
            # Tune's JSON and CSV loggers: result.json / progress.csv per trial, what ExperimentAnalysis and
            # ResultGrid.get_dataframe() read (one row per trial: its cell ids, final metrics). A few lines per
            # trial; the rows stay in Parquet (docs/sweeps.md, "Ray Tune's readers").
            callbacks=[callback, *_tune_result_logs()], stop=DiskFullStopper(),
        ),
    )


# ---- public entry points ------------------------------------------------------------------------
def run_plan(plan: Plan, options: RunOptions | None = None, stream: TextIO | None = None) -> SweepResult:
    """Run (or continue) the sweep of `plan` (see the module docstring) as `options` say."""
    options = options or RunOptions()
    options.check()
    return _run(plan, options, stream)


def run_sweep(space: str, *, name: str | None = None, options: RunOptions | None = None,
              stream: TextIO | None = None) -> SweepResult:
    """Run (or continue) the sweep ``name`` (default: the space's name) over ``space``."""
    (options or RunOptions()).check()
    return run_plan(Plan.from_space(space, name), options, stream)


def resume_sweep(name: str, *, options: RunOptions | None = None, stream: TextIO | None = None) -> SweepResult:
    """Continue a sweep from its manifest (no space file needed), with the packing it was started with."""
    options = options or RunOptions()
    options.check()
    return run_plan(Plan.from_sweep(options.results, name), options, stream)


@contextmanager
def _disk_full_is_one_line(sweep_dir: AnyPath, name: str, results: str | Path) -> Iterator[None]:
    """A full disk, met by a worker (DiskFullStopper) or by this driver, ends the sweep as DiskFull: one line
    with the path, what is kept and the command that continues. Finished cells are untouched; a write that
    failed left only a temp file, removed (or a name the reader never counts)."""
    try:
        yield
    except OSError as e:
        if not is_disk_full(e):
            raise
        where = getattr(e, "filename", None) or sweep_dir
        try:
            kept = f"{len(store.done_cell_ids(sweep_dir))} finished cells are kept"
        except OSError:
            kept = "finished cells are kept"
        raise DiskFull(f"no space left on the device of {where}: the sweep stopped, {kept}; free some space, "
                       f"then: asp-dist resume {name} --results {results}") from None


def _record_provenance(sweep_dir: AnyPath, plan: Plan, stream: TextIO, ray_nodes: list | None = None,
                       tracking: TrackingSettings | None = None) -> None:
    """env/<n>/ of this run (asp_dist.sweep.provenance); a record that cannot be written is a warning, never
    a stop (a full disk is the run's to report, when it writes what counts)."""
    try:
        provenance.record(sweep_dir, space_text=plan.space_text, ray_nodes=ray_nodes,
                          tracking=None if tracking is None else tracking.to_dict(),
                          grid=f"space {plan.space}, {len(plan.specs)} cells, grid hash {grid_hash(plan.specs)}")
    except (OSError, StorageError) as e:
        stream.write(f"asp-dist: warning: the run's environment was not recorded under {sweep_dir}/env ({e})\n")


def _run(plan: Plan, options: RunOptions, stream: TextIO | None) -> SweepResult:
    specs, space, name = plan.specs, plan.space, plan.name
    results, workers, address = options.results, options.workers, options.address
    max_failures, checkpoint_every_s, connect_timeout_s = (options.max_failures, options.checkpoint_every_s,
                                                           options.connect_timeout_s)
    pack, pack_size = options.pack, options.pack_size
    sweep_dir = ledger.sweep_dir_for(results, name)
    stream = stream or sys.stderr
    grid = {s.cell_id: f"{s.domain}/{s.method}" for s in specs}

    def session():
        return ray_session(workers, address, options.ray_temp_dir, dashboard=options.dashboard,
                           connect_timeout_s=connect_timeout_s, stream=stream)

    with signals.sigterm_as_interrupt(), _disk_full_is_one_line(sweep_dir, name, results):
        # The manifest as the plan's checks read it (the CLI's); read here only when the plan was made elsewhere.
        seen = store.read_manifest(sweep_dir) if plan.manifest is preflight.UNREAD else plan.manifest
        if address:  # a cluster that does not answer is refused before anything is written
            preflight.check_sweep_dir_readonly(sweep_dir, seen)
            resolve_packing(pack, pack_size, seen)
            preflight.check_address(address, connect_timeout_s)
        # A cluster is joined before the sweep dir is written; the embedded Ray starts only if a cell is pending.
        with session() if address else nullcontext():
            preflight.check_sweep_dir(sweep_dir, seen)
            with ledger.sweep_lock(sweep_dir, connect_timeout_s=connect_timeout_s):
                stored = store.read_manifest(sweep_dir)  # once under the lock: another run may have changed it
                packing = resolve_packing(pack, pack_size, stored)  # refuses another one
                # refuses a different grid (with --extend: one that only adds cells grows the sweep)
                manifest = preflight.check_manifest(sweep_dir, name, specs, space, packing, extend=options.extend,
                                                    manifest=stored)
                if stored is None or stored["grid_hash"] != manifest["grid_hash"]:  # before any new cell runs
                    store.write_manifest(sweep_dir, manifest)
                if not isinstance(sweep_dir, S3Path):  # on S3 checkpoints are staged in Ray's scratch
                    shutil.rmtree(sweep_dir / TUNE_DIR / CKPT_TMP, ignore_errors=True)  # a killed worker's leftovers
                # A cell file the reader rejects (cut short, empty, another cell's, a dangling link) would keep its
                # cell pending for ever: kept aside for inspection, and the cell trains again.
                for path, moved_to, problem in store.set_aside_damaged(sweep_dir, {s.cell_id: (s.domain, s.method)
                                                                                   for s in specs}):
                    stream.write(f"asp-dist: warning: {path} {problem}: moved to {moved_to}; the cell trains again\n")
                done, _ = ledger.finished_and_failed(sweep_dir, grid, remember=True)  # status reads no footer again
                # Units from the whole grid (never from what is left): a resumed pack is the same pack.
                units = make_units(specs, packing)
                pending = schedule([u for u in units if not set(u.cell_ids) <= done], packing, sweep_dir)
                bases = sum(u.base_only for u in pending)  # trained first, one per free worker, then the packs
                counter = SweepCounter(name, grid, done, stream=stream, where=str(store.cells_dir(sweep_dir)),
                                       bases=bases)
                where = f"cluster {address}" if address else f"embedded Ray, {workers} worker(s)"
                how = (f", packed ({packing.describe()}: {describe_units(units)}"
                       f"{f'; {bases} base(s) missing: trained first' if bases else ''})") if packing.packed else ""
                stream.write(f"sweep {name}: space {space}, {len(specs)} cells ({len(done)} already done){how}, "
                             f"{where}, results in {sweep_dir}\n")
                if pending:
                    callback = SweepCallback(str(sweep_dir), name, grid, counter)
                    _DISK_FULL.clear()
                    with nullcontext() if address else session():
                        _record_provenance(sweep_dir, plan, stream, ray_nodes=ray.nodes(), tracking=options.tracking)
                        with _trackers(plan, options.tracking, stream), _no_callback_tag_without_usage_stats(), \
                                nullcontext() if address else worker_start.trainables_without_runtime_env():
                            _run_tune(sweep_dir, callback, pending, workers, max_failures, checkpoint_every_s)
                    if _DISK_FULL:
                        raise OSError(errno.ENOSPC, "No space left on device", _DISK_FULL[0] or str(sweep_dir))
                else:  # a run that trains nothing records nothing (no env/<n>/, locally or on S3)
                    stream.write(f"sweep {name}: every cell is done; nothing to run\n")
                done, failed = ledger.finished_and_failed(sweep_dir, grid, remember=True)
                counter.update(done=done, failed=failed, running=set(), last_failure=last_failure(sweep_dir, failed))
                counter.finish()
                return SweepResult(name, sweep_dir, len(specs), len(done), len(failed))
