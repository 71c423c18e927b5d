"""The sweep service on Ray Tune: one trial per cell, results in the store. The only Ray module.

Flow of ``run_sweep`` / ``resume_sweep``:

1. validate everything a user can get wrong (space, name, results dir, grid vs. manifest, lock)
   before anything is written (asp_dist.sweep.ledger, no Ray);
2. take the sweep's lock (``results/<sweep>/.lock``, fcntl: released by the OS even after SIGKILL);
3. drop the cells that already have a Parquet file (the record that a cell is done);
4. start an embedded Ray (or join ``--address``: that connection is made, within
   ``--connect-timeout``, before anything is written) and run one Tune trial per remaining cell,
   1 CPU each, ``reuse_actors=True``, at most ``workers`` at once. If the previous run of this
   sweep was interrupted, its Tune experiment is restored (``Tuner.restore``) so running cells
   continue from their last checkpoint (``tune.get_checkpoint``);
5. each trial gets its base from the shared cache, runs ``run_cell`` (checkpointing through
   ``tune.report(..., checkpoint=...)``) and writes its row through ``asp_dist.results.store``.

With ``--pack trial|method`` (asp_dist.sweep.packing) a trial may instead train a *pack*: cells of one
domain trained as one batched model (asp_dist.training.packed). The packs are a function of the grid
and the packing stored in the manifest, so a resumed sweep rebuilds the same packs; a pack trains
whole and writes only its members without a row, each as a cell would (row, curve, failure).

A worker that dies is retried ``max_failures`` times from its last checkpoint; a cell that
still fails (or fails deterministically, e.g. a base that never meets its bar) is recorded
under ``failed/`` and the sweep goes on. ``resume`` retries failed cells.

With ``--results s3://bucket/prefix`` the same flow runs on object storage: cell rows, failures, the
manifest and the bases go to the bucket through the store, the lock is a lease (ledger), and Tune's
experiment state and checkpoints go to ``<sweep>/tune/`` in the bucket through
``RunConfig(storage_path=..., storage_filesystem=pyarrow S3FileSystem)``; a checkpoint is staged in
the trial's working directory under the Ray temp dir (node-local scratch) before Tune uploads it.

Nothing is left behind: checkpoints are staged under the sweep's own ``tune/.ckpt-tmp/``; SIGTERM
stops a sweep as Ctrl-C does (ledger.sigterm_as_interrupt); a reaper process ends the embedded
Ray's processes within seconds when the driver dies, even by SIGKILL; and old session
directories of the embedded Ray are pruned at start.
"""

from __future__ import annotations

import errno
import getpass
import json
import logging
import os
import secrets
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import ExitStack, contextmanager, nullcontext
from pathlib import Path
from typing import Any, Iterator, TextIO

# Before Ray is imported: no usage stats, no Tune CSV/JSON/TensorBoard loggers per trial.
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("TUNE_DISABLE_AUTO_CALLBACK_LOGGERS", "1")
os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
# Short cells finish in bursts and each one snapshots the experiment: Tune then warns every few
# seconds that snapshots "may become a bottleneck" (they cost milliseconds here). Keep the log readable.
os.environ.setdefault("TUNE_WARN_EXCESSIVE_EXPERIMENT_CHECKPOINT_SYNC_THRESHOLD_S", "0")

import ray  # noqa: E402
import torch  # noqa: E402
from ray import tune  # noqa: E402
from ray.exceptions import AuthenticationError  # noqa: E402

from asp_dist.data.mnist import MNISTError  # noqa: E402
from asp_dist.errors import DiskFull, SpecError, StorageError, SweepError, is_disk_full  # noqa: E402
from asp_dist.results import store  # noqa: E402
from asp_dist.results.location import AnyPath, S3Path, as_path, filesystem, write_replace  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.sweep import ledger  # noqa: E402
from asp_dist.sweep import reaper as reaper_program  # noqa: E402
from asp_dist.sweep.base_cache import get_base  # noqa: E402
from asp_dist.sweep.ledger import SweepResult  # noqa: E402
from asp_dist.sweep.packing import Unit, describe_units, make_units, resolve_packing  # noqa: E402
from asp_dist.sweep.plan import Plan, RunOptions  # noqa: E402
from asp_dist.sweep.progress import SweepCounter  # noqa: E402
from asp_dist.training import packed  # noqa: E402
from asp_dist.training.bases import BaseRejected  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402
from asp_dist.training.packed.single import CellDiverged  # noqa: E402

__all__ = ["run_sweep", "resume_sweep", "SweepResult", "train_cell"]

OBJECT_STORE_BYTES = 100 * 1024**2  # cells exchange no large objects; Ray's minimum is ~75 MB
TUNE_DIR = "tune"
TUNE_CURRENT = "current.json"  # which Tune experiment covers which cells
CKPT_TMP = ".ckpt-tmp"  # under TUNE_DIR: checkpoints being written, before Tune copies them into its trial dir
RAY_SESSIONS_KEPT = 3  # session_* dirs of the embedded Ray kept at start (logs of the last runs)
RAY_SESSION_MIN_AGE_S = 300.0  # a younger session may belong to a Ray that is starting: never pruned

log = logging.getLogger(__name__)


# ---- the Tune trial: one cell, or one pack of cells ---------------------------------------------
def train_cell(config: dict[str, Any]) -> None:
    """Function trainable. Must keep no state between calls: actors are reused across cells.

    ``config["cell"]`` is one cell's config, or a pack's (it has a ``pack_id``: train_pack). A full disk is
    not a crash to retry: the trial reports it (``disk_full``) and the driver stops the sweep (DiskFullStopper);
    whatever was being written is a temp file that is removed, never a file that counts."""
    torch.set_num_threads(1)
    config = config["cell"]
    try:
        train_pack(config) if "pack_id" in config else _train_one_cell(config)
    except OSError as e:
        if not is_disk_full(e):
            raise
        tune.report({"cell_done": 0, DISK_FULL: getattr(e, "filename", None) or config["sweep_dir"]})


def _train_one_cell(config: dict[str, Any]) -> None:
    spec = CellSpec.from_dict(config["spec"])
    sweep_dir = as_path(config["sweep_dir"])
    cell_id = config["cell_id"]
    if store.is_done(sweep_dir, spec.domain, spec.method, cell_id):
        tune.report({"cell_done": 1, "skipped": 1})  # finished before Tune's state caught up
        return
    restore = _restored_state()
    save = _checkpointer(sweep_dir, cell_id)
    try:
        base, _ = get_base(spec, store.bases_dir(sweep_dir))
        curve: list[dict[str, float]] = []
        row = run_cell(spec, base=base, checkpoint=save, restore=restore,
                       checkpoint_every_s=config["checkpoint_every_s"], curve=curve)
    except StorageError:
        raise  # object storage that did not answer: a crash, retried from the last checkpoint
    except (SpecError, BaseRejected, MNISTError, CellDiverged) as e:
        # Deterministic (a bad spec, a base that never meets its bar, missing or corrupt data, a cell
        # whose training diverged): a retry would fail the same way. Record it once and let the
        # sweep go on; `resume` tries it again.
        store.record_failure(sweep_dir, cell_id, spec.domain, spec.method, f"{type(e).__name__}: {e}")
        tune.report({"cell_done": 0, "cell_failed": 1})
        return
    row["ray_node_id"] = ray.get_runtime_context().get_node_id()
    row["ray_version"] = ray.__version__
    store.write_curve(sweep_dir, row, curve)
    store.write_row(sweep_dir, row, config["sweep_id"])
    store.clear_failure(sweep_dir, cell_id)
    tune.report({"cell_done": 1, "eval_mixed": float(row["eval_mixed"])})


def _restored_state() -> dict | None:
    """The state of the trial's last checkpoint (a restarted or restored trial), else None."""
    checkpoint = tune.get_checkpoint()
    if checkpoint is None:
        return None
    with checkpoint.as_directory() as d:
        return torch.load(Path(d) / "state.pt", weights_only=False)


def _checkpointer(sweep_dir: AnyPath, name: str):
    """save(state): one checkpoint of the trial through tune.report."""
    # On S3 the sweep has no local directory: stage in the trial's working directory, which Tune keeps
    # under the Ray temp dir (node-local scratch, pruned with its session).
    staging = Path.cwd() / CKPT_TMP if isinstance(sweep_dir, S3Path) else sweep_dir / TUNE_DIR / CKPT_TMP

    def save(state: dict) -> None:
        # Staged in the sweep's own tree (never the system temp dir: it may be small, shared or wiped),
        # written under a temp name and renamed, and removed once report() returns: Tune has copied
        # it into the trial's storage by then.
        staging.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f"{name}-", dir=staging) as d:
            part = Path(d) / ".state.pt.part"
            torch.save(state, part)
            os.replace(part, Path(d) / "state.pt")
            tune.report({"cell_done": 0, "step": state["trainer"]["step"]},
                        checkpoint=tune.Checkpoint.from_directory(d))

    return save


def train_pack(config: dict[str, Any]) -> None:
    """One pack (asp_dist.sweep.packing): its cells trained together by their domain's packed trainer.

    The whole pack trains even when some members already have a row (so that every member's row is
    the one an uninterrupted run writes); only members without a row are written. A restarted trial
    continues from the pack's last checkpoint. Failures are per member, as a single cell's: a base
    that never meets its bar, or a member that diverged, is recorded for that member only."""
    specs = [CellSpec.from_dict(d).resolved() for d in config["specs"]]
    sweep_dir = as_path(config["sweep_dir"])
    pack_id = config["pack_id"]
    todo = {s.cell_id for s in specs if not store.is_done(sweep_dir, s.domain, s.method, s.cell_id)}
    if not todo:
        tune.report({"cell_done": 1, "skipped": 1})  # finished before Tune's state caught up
        return
    restore = _restored_state()
    failures: dict[str, str] = {}
    bases: dict[str, Any] = {}
    for spec in specs:  # one base per key from the sweep's cache, as single cells get theirs
        if spec.base_key in bases or spec.cell_id in failures:
            continue
        try:
            bases[spec.base_key], _ = get_base(spec, store.bases_dir(sweep_dir))
        except StorageError:
            raise
        except (SpecError, BaseRejected, MNISTError) as e:
            why = f"{type(e).__name__}: {e}"
            failures.update({s.cell_id: why for s in specs if s.base_key == spec.base_key})
    live = [s for s in specs if s.cell_id not in failures]
    composition = (pack_id, [s.cell_id for s in live])
    if restore is not None and (restore.get("pack_id"), restore.get("cell_ids")) != composition:
        restore = None  # another composition (a base was rejected or accepted since): start over
    save = _checkpointer(sweep_dir, config["name"])
    results = []
    if live:
        try:
            results = packed.run_pack(live, bases=bases, curves=True, checkpoint=lambda state: save(
                dict(state, pack_id=pack_id)), restore=restore, checkpoint_every_s=config["checkpoint_every_s"])
        except StorageError:
            raise
        except (SpecError, BaseRejected, MNISTError) as e:
            failures.update({s.cell_id: f"{type(e).__name__}: {e}" for s in live})
    written = 0
    for result in results:
        spec = result.spec
        if spec.cell_id not in todo:
            continue  # a row written before (e.g. by the interrupted run of this pack): never rewritten
        if result.row is None:
            failures[spec.cell_id] = f"in pack {pack_id}: {result.error}"
            continue
        row = dict(result.row, pack=pack_id, ray_node_id=ray.get_runtime_context().get_node_id(),
                   ray_version=ray.__version__)
        store.write_curve(sweep_dir, row, result.curve or [])
        written += store.write_row(sweep_dir, row, config["sweep_id"])
        store.clear_failure(sweep_dir, spec.cell_id)
    for spec in specs:
        if spec.cell_id in failures and spec.cell_id in todo:
            store.record_failure(sweep_dir, spec.cell_id, spec.domain, spec.method, failures[spec.cell_id])
    tune.report({"cell_done": int(not failures), "cells_written": written, "cell_failed": len(failures)})


def unit_config(unit: Unit, sweep_dir: AnyPath, sweep_id: str, checkpoint_every_s: float) -> dict[str, Any]:
    """What a Tune trial gets: a cell's config (as before packs existed), or a pack's."""
    common = {"sweep_dir": str(sweep_dir), "sweep_id": sweep_id, "checkpoint_every_s": checkpoint_every_s}
    if unit.pack_id is None:
        spec = unit.specs[0]
        return {"spec": spec.to_dict(), "cell_id": spec.cell_id, **common}
    return {"pack_id": unit.pack_id, "name": unit.name, "specs": [s.to_dict() for s in unit.specs],
            "cell_ids": unit.cell_ids, **common}


def _config_cells(config: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(cell id, domain, method) of every cell a trial's config runs."""
    if "pack_id" in config:
        return [(cid, s["domain"], s["method"]) for cid, s in zip(config["cell_ids"], config["specs"])]
    return [(config["cell_id"], config["spec"]["domain"], config["spec"]["method"])]


def trial_name(trial) -> str:
    """A trial's name and directory are its cell id, or its pack's name (a worker's working directory ends
    with it)."""
    config = trial.config["cell"]
    return config["name"] if "pack_id" in config else config["cell_id"]


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
            done, _ = ledger.finished_and_failed(as_path(self.sweep_dir), self.grid)
            self.counter = SweepCounter(self.name, self.grid, done, where=self.sweep_dir)
        return self.counter

    @staticmethod
    def _running(trials) -> set[str]:
        """The cells of the running trials (every member of a running pack: counts are per cell)."""
        return {cell_id for t in trials if t.status == "RUNNING" for cell_id, _, _ in _config_cells(t.config["cell"])}

    def _refresh(self, trials) -> None:
        done, failed = ledger.finished_and_failed(as_path(self.sweep_dir), self.grid)
        self._counter().update(done=done, failed=failed, running=self._running(trials),
                               last_failure=last_failure(as_path(self.sweep_dir), failed))

    def on_trial_result(self, iteration, trials, trial, result, **info):
        if result.get(DISK_FULL) and not _DISK_FULL:
            _DISK_FULL.append(str(result[DISK_FULL]))

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
        config = trial.config["cell"]
        where = f" (in pack {config['pack_id']})" if "pack_id" in config else ""
        sweep_dir = as_path(self.sweep_dir)
        for cell_id, domain, method in _config_cells(config):
            if not store.is_done(sweep_dir, domain, method, cell_id):
                store.record_failure(sweep_dir, cell_id, domain, method,
                                     f"failed after {trial.num_failures} attempt(s){where}: {error}")
        self._refresh(trials)


DISK_FULL = "disk_full"  # a trial's result key: where a write found no space left
_DISK_FULL: list[str] = []  # this driver's: set by SweepCallback, read by DiskFullStopper and _run


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
    this driver process's, _DISK_FULL, so that a restored experiment's unpickled stopper sees it too.)"""

    def __call__(self, trial_id, result) -> bool:
        return bool(result.get(DISK_FULL))

    def stop_all(self) -> bool:
        return bool(_DISK_FULL)


def last_failure(sweep_dir: AnyPath, failed: set[str]) -> str:
    """The newest failure of the grid, as "cell id: last line of its error"."""
    records = [r for cell_id, r in store.failed_cells(sweep_dir).items() if cell_id in failed]
    if not records:
        return ""
    newest = max(records, key=lambda r: str(r.get("failed_at", "")))
    return f"{newest['cell_id']}: {store.last_error_line(newest)}"


# ---- Ray ----------------------------------------------------------------------------------------
LOOPBACK = "127.0.0.1"


@contextmanager
def loopback_only() -> Iterator[None]:
    """The environment of an embedded Ray that nobody else can reach: every server of it (GCS, raylet,
    object manager, workers, the driver's own) binds 127.0.0.1, and it asks for a token anyway.

    Loopback: Ray binds a node's servers to the loopback address only when its node IP is 127.0.0.1, and
    it keeps that IP (instead of swapping in the machine's address) only in its single-machine mode,
    RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 -- read from the environment by the processes it starts, and
    at import by this one, hence the constant set too. Token: loopback is open to every local user of
    a shared machine, so with RAY_AUTH_MODE unset Ray's own default for a new local cluster (token
    authentication) stays on, with a random per-process RAY_AUTH_TOKEN where the user configured none
    (no RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token): it lives in the environment of this
    process and of the Ray processes it starts, and nothing is written to ~/.ray. RAY_AUTH_MODE set by
    the user is theirs. tests/test_sweep.py checks the listening sockets of a running sweep."""
    from ray._private import ray_constants

    keys = (ray_constants.ENABLE_RAY_CLUSTERS_ENV_VAR, "RAY_AUTH_MODE", "RAY_AUTH_TOKEN")
    saved_env = {k: os.environ.get(k) for k in keys}
    saved_flag = ray_constants.ENABLE_RAY_CLUSTER
    os.environ[ray_constants.ENABLE_RAY_CLUSTERS_ENV_VAR] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    configured = (os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                  or (Path.home() / ".ray" / "auth_token").is_file())
    if "RAY_AUTH_MODE" not in os.environ and not configured:
        os.environ["RAY_AUTH_TOKEN"] = _session_token()
    # Ray says at every start that it turned token authentication on: that is the expected state here.
    auth_log = logging.getLogger("ray._private.authentication.authentication_token_setup")
    level = auth_log.level
    auth_log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        auth_log.setLevel(level)
        ray_constants.ENABLE_RAY_CLUSTER = saved_flag
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


_TOKEN: list[str] = []


def _session_token() -> str:
    """One random token per process: Ray's token loader caches the first one it reads."""
    if not _TOKEN:
        _TOKEN.append(secrets.token_hex(32))
    return _TOKEN[0]


RAY_TEMP_ENV = "ASP_DIST_RAY_TEMP_DIR"  # the default of --ray-temp-dir (the test suite sets one per xdist worker)


def default_ray_temp_dir() -> str:
    """Short (Unix sockets live under it, ~107-char limit) and per user, never a bare /tmp/ray."""
    return os.environ.get(RAY_TEMP_ENV) or f"/tmp/asp-ray-{getpass.getuser()}"


@contextmanager
def ray_session(workers: int, address: str | None, temp_dir: str | None, *, dashboard: bool = False,
                connect_timeout_s: float = ledger.DEFAULT_CONNECT_TIMEOUT_S,
                stream: TextIO | None = None) -> Iterator[None]:
    """Ray for one run: joined at ``address`` within ``connect_timeout_s``, or embedded (its old
    session dirs pruned, no dashboard unless asked, and then on 127.0.0.1 only, a reaper that ends
    its processes when this process dies). Shut down on the way out, however the run ends."""
    if ray.is_initialized():
        raise SweepError("Ray is already initialised in this process; run the sweep in a fresh process")
    common = dict(log_to_driver=False, logging_level=logging.WARNING, configure_logging=True)
    main_thread = threading.current_thread() is threading.main_thread()
    sigterm = signal.getsignal(signal.SIGTERM) if main_thread else None
    reaper = None
    stack = ExitStack()  # the embedded Ray's environment, put back after its shutdown
    try:
        try:
            if address:
                with _connect_deadline(address, connect_timeout_s):
                    ray.init(address=address, **common)
            else:
                # Absolute: the reaper finds Ray's processes by this path in their command lines.
                temp_dir = os.path.abspath(os.path.expanduser(temp_dir or default_ray_temp_dir()))
                for pruned in prune_ray_sessions(temp_dir):
                    log.info("pruned old Ray session %s", pruned)
                prune_reaper_logs(temp_dir)
                reaper = _start_reaper(temp_dir)
                stack.enter_context(loopback_only())
                with _signals_held(sigterm):
                    context = ray.init(address="local", num_cpus=workers, _temp_dir=temp_dir, _node_ip_address=LOOPBACK,
                                       include_dashboard=dashboard, dashboard_host=LOOPBACK,
                                       object_store_memory=OBJECT_STORE_BYTES, **common)
                if dashboard and context.dashboard_url:
                    (stream or sys.stderr).write(f"Ray dashboard: http://{context.dashboard_url}\n")
        except ConnectionError as e:
            raise SweepError(f"cannot connect to the Ray cluster at {address}: {e}{_token_hint()}") from None
        except AuthenticationError as e:  # the cluster wants a token this process lacks, or another one
            first = str(e).strip().splitlines()[0] if str(e).strip() else "token refused"
            raise SweepError(f"the Ray cluster at {address} refused this process ({first}); give it the cluster's "
                             f"token: RAY_AUTH_MODE=token and RAY_AUTH_TOKEN (or RAY_AUTH_TOKEN_PATH), see "
                             f"docs/sweeps.md, Security") from None
        finally:
            # ray.init sets its own SIGTERM handler (sys.exit); put back the sweep's (ledger.sigterm_as_interrupt).
            if sigterm is not None:
                signal.signal(signal.SIGTERM, sigterm)
        yield
    finally:
        try:
            ray.shutdown()
        finally:
            _stop_reaper(reaper)
            stack.close()


@contextmanager
def _signals_held(sigterm) -> Iterator[None]:
    """While the embedded Ray starts: a SIGTERM is held, not lost, and handled once ray.init returns.

    ray.init installs SIGTERM handlers of its own (a driver's sys.exit, a node's drain-then-exit) that a
    SIGTERM during start-up would run inside Ray's code, where it was seen to vanish (the sweep went on).
    Here Ray's installer does nothing for the duration, a SIGTERM is only noted, and the sweep's own
    handler (ledger.sigterm_as_interrupt) gets it as soon as Ray is up: the sweep stops as it does later,
    with ray_session's cleanup. A no-op off the main thread or without a sweep handler."""
    if sigterm is None or not callable(sigterm):
        yield
        return
    from ray._private import utils as ray_utils

    held: list[int] = []
    installer = ray_utils.set_sigterm_handler
    ray_utils.set_sigterm_handler = lambda handler: None
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        ray_utils.set_sigterm_handler = installer
        signal.signal(signal.SIGTERM, previous)
    if held:
        sigterm(held[0], None)  # raises KeyboardInterrupt: the sweep stops, ray_session shuts Ray down


def _token_hint() -> str:
    """Ray retries a refused token until it gives up as if nobody answered: say what may be missing."""
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "token" and (
            os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
            or (Path.home() / ".ray" / "auth_token").is_file()):
        return " (or the cluster's token differs from this process's)"
    return ("; a cluster with token authentication also needs RAY_AUTH_MODE=token and RAY_AUTH_TOKEN "
            "(docs/sweeps.md, Security)")


def _hard_exit(code: int, message: str) -> None:
    try:
        os.write(2, (message + "\n").encode())
    finally:
        os._exit(code)


@contextmanager
def _connect_deadline(address: str, timeout_s: float) -> Iterator[None]:
    """Bound ray.init(address=...). It waits for an unresponsive head for minutes inside Ray's C++ client,
    where neither exceptions nor signal handlers reach it; a watcher thread ends the process instead:
    exit 2 at the deadline, 128+N on SIGINT/SIGTERM. Nothing has been written by then (see _run)."""
    done = threading.Event()
    wake_r = wake_w = None
    if threading.current_thread() is threading.main_thread():
        # The C-level signal handler writes the signal number here even while the main thread is stuck.
        wake_r, wake_w = os.pipe()
        os.set_blocking(wake_w, False)
        previous_wakeup = signal.set_wakeup_fd(wake_w, warn_on_full_buffer=False)

    def watch() -> None:
        deadline = time.monotonic() + timeout_s
        while not done.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                _hard_exit(2, f"asp-dist: error: no answer from the Ray cluster at {address} within "
                              f"{timeout_s:g} s; check --address, or raise --connect-timeout{_token_hint()}")
            if wake_r is None:
                done.wait(min(remaining, 0.5))
                continue
            ready, _, _ = select.select([wake_r], [], [], min(remaining, 0.5))
            for signum in (os.read(wake_r, 64) if ready else b""):
                if signum in (signal.SIGINT, signal.SIGTERM) and not done.wait(1.0):
                    # The main thread did not get to its handler within a second: it is inside Ray's wait.
                    _hard_exit(128 + signum, f"asp-dist: interrupted while connecting to the Ray cluster at {address}")

    watcher = threading.Thread(target=watch, name="asp-connect-deadline", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join(5)
        if wake_r is not None:
            signal.set_wakeup_fd(previous_wakeup)
            os.close(wake_r)
            os.close(wake_w)


# ---- the embedded Ray's processes and session dirs --------------------------------------------------
# The reaper (asp_dist/sweep/reaper.py, run by path: standard library only) kills what is left of the
# embedded Ray when the driver ends, however it ends; it watches a pipe whose other end only the driver holds.
def _start_reaper(temp_dir: str) -> tuple[subprocess.Popen, int] | None:
    """The reaper of the embedded Ray about to start (Linux: it reads /proc), and the pipe it watches."""
    if not os.path.isdir("/proc/self"):
        return None
    read_end, write_end = os.pipe()  # not inheritable: only the reaper gets an end of it
    try:
        proc = subprocess.Popen([sys.executable, "-I", "-S", reaper_program.__file__, str(os.getpid()), temp_dir],
                                stdin=read_end, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError as e:
        os.close(write_end)
        log.warning("no reaper for the embedded Ray (%s): its processes may outlive a killed driver", e)
        return None
    finally:
        os.close(read_end)
    return proc, write_end


def _stop_reaper(reaper: tuple[subprocess.Popen, int] | None) -> None:
    """After ray.shutdown: the reaper kills any straggler and exits."""
    if reaper is None:
        return
    proc, write_end = reaper
    os.close(write_end)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _processes_using(root: Path) -> set[str]:
    """Names of the session dirs under ``root`` that a live process names in its command line, works in,
    or holds a file of (Linux /proc; unreadable processes are skipped)."""
    prefix = f"{root}/session_"
    used: set[str] = set()

    def note(text: str) -> None:
        start = text.find(prefix)
        while start >= 0:
            used.add(text[start + len(prefix) - len("session_"):].split("/", 1)[0].split()[0])
            start = text.find(prefix, start + 1)

    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            note((proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"))
            note(os.readlink(proc / "cwd"))
            for fd in (proc / "fd").iterdir():
                note(os.readlink(fd))
        except OSError:
            continue
    return used


def prune_ray_sessions(temp_dir: str | Path, keep: int = RAY_SESSIONS_KEPT,
                       min_age_s: float = RAY_SESSION_MIN_AGE_S) -> list[Path]:
    """Remove old ``session_*`` dirs of an embedded Ray's temp dir, keeping the newest ``keep``, and
    never one that ``session_latest`` points to, that changed in the last ``min_age_s`` seconds, whose
    driver is alive, or that a live process uses. Returns the removed dirs. Needs /proc: elsewhere,
    and when the dir cannot be read, nothing is removed."""
    root = Path(temp_dir).expanduser().absolute()
    if not root.is_dir() or not os.path.isdir("/proc/self"):
        return []
    try:
        sessions = sorted((p for p in root.iterdir() if p.name.startswith("session_") and p.name != "session_latest"
                           and not p.is_symlink() and p.is_dir()), key=lambda p: p.name, reverse=True)
    except OSError:
        return []
    candidates = sessions[keep:]  # the names sort by start time: session_<date>_<time>_<us>_<driver pid>
    if not candidates:
        return []
    latest = root / "session_latest"
    latest = latest.resolve() if latest.is_symlink() else None
    used = _processes_using(root)
    removed = []
    now = time.time()
    for session in candidates:
        try:
            changed = max(session.stat().st_mtime, *(p.stat().st_mtime for p in session.iterdir()))
        except (OSError, ValueError):
            continue
        driver = session.name.rsplit("_", 1)[-1]
        if (session.resolve() == latest or now - changed < min_age_s or session.name in used
                or (driver.isdigit() and Path(f"/proc/{driver}").exists())):
            continue
        shutil.rmtree(session, ignore_errors=True)
        if not session.exists():
            removed.append(session)
    return removed


def prune_reaper_logs(temp_dir: str | Path, keep: int = RAY_SESSIONS_KEPT) -> None:
    """Keep the reaper logs of the newest ``keep`` drivers (and of any driver still alive)."""
    logs = sorted(Path(temp_dir).glob("reaper-*.log"), key=lambda p: p.stat().st_mtime, reverse=True)
    for old in logs[keep:]:
        driver = old.stem.removeprefix("reaper-")
        if not (driver.isdigit() and Path(f"/proc/{driver}").exists()):
            old.unlink(missing_ok=True)


def _tune_storage(sweep_dir: AnyPath) -> tuple[str, Any]:
    """Where Tune keeps the sweep's experiments: (storage_path, storage_filesystem). On S3 the path is
    ``bucket/prefix/<sweep>/tune`` on pyarrow's S3FileSystem (its endpoint from AWS_ENDPOINT_URL, its
    credentials from each node's AWS chain: the pickled filesystem carries none)."""
    if isinstance(sweep_dir, S3Path):
        return (sweep_dir / TUNE_DIR).fs_path, filesystem()
    return str(sweep_dir / TUNE_DIR), None


def _tune_experiment(sweep_dir: AnyPath, pending: list[Unit], allow_restore: bool = True) -> tuple[str, bool]:
    """Name of the Tune experiment to run, and whether to restore it.

    An interrupted experiment is restored when it covers every pending cell (then its running
    trials continue from their checkpoints); otherwise a new experiment over just the pending
    cells (and packs) starts (e.g. after a clean finish with failures, or when the state is unreadable).
    """
    tune_root = sweep_dir / TUNE_DIR
    current_path = tune_root / TUNE_CURRENT
    pending_ids = {cell_id for unit in pending for cell_id in unit.cell_ids}
    if current_path.exists():
        current = json.loads(current_path.read_text())
        storage_path, storage_fs = _tune_storage(sweep_dir)
        exp_path = f"{storage_path}/{current['experiment']}"
        if allow_restore and pending_ids <= set(current["cells"]) and tune.Tuner.can_restore(
                exp_path, storage_filesystem=storage_fs) and _state_readable(tune_root / current["experiment"]):
            return current["experiment"], True
        number = int(current["experiment"].rsplit("-", 1)[1]) + 1
    else:
        number = 1
    experiment = f"run-{number}"
    write_replace(current_path, json.dumps({"experiment": experiment, "cells": sorted(pending_ids)}))
    return experiment, False


def _state_readable(experiment_dir: AnyPath) -> bool:
    """Tune's newest experiment state there is whole JSON. A write cut short (a full disk, a crash of the
    disk) would make Tune's restore fail with a traceback; the sweep then starts a new experiment instead,
    and the running cells' checkpoints are lost, not their rows."""
    try:  # (the trials' state; basic-variant-state-*.json beside it is a pickle despite its name)
        states = sorted(experiment_dir.glob("experiment_state-*.json"), key=lambda p: p.name)
        if states:
            json.loads(states[-1].read_text())
        return True
    except (OSError, ValueError):
        log.warning("Tune's state in %s cannot be read; the pending cells start a new experiment", experiment_dir)
        return False


def _run_tune(sweep_dir: AnyPath, callback: SweepCallback, pending: list[Unit], workers: int, max_failures: int,
              checkpoint_every_s: float) -> None:
    # Rows live in Parquet, not in Tune's per-trial logs (disabled above): silence Tune's
    # complaint that it cannot build its own result table from them.
    logging.getLogger("ray.tune.analysis.experiment_analysis").setLevel(logging.ERROR)
    state_log = logging.getLogger("ray.tune.execution.experiment_state")
    if not any(isinstance(f, _DiskFullLogFilter) for f in state_log.filters):
        state_log.addFilter(_DiskFullLogFilter())
    experiment, restore = _tune_experiment(sweep_dir, pending)
    if restore:
        try:
            _fit(_restored_tuner(sweep_dir, experiment))
        except Exception as e:  # noqa: BLE001 - an unreadable Tune state must not block the sweep
            log.warning("could not restore Tune experiment %s (%s); starting a new one", experiment, e)
        # Tune does not rerun trials it saw finish, e.g. a cell that failed deterministically
        # (recorded under failed/): whatever is still missing runs in a fresh experiment (a pack with
        # a missing member as the whole pack).
        pending = [u for u in pending if not all(store.is_done(sweep_dir, s.domain, s.method, s.cell_id)
                                                 for s in u.specs)]
        if not pending:
            return
        experiment, _ = _tune_experiment(sweep_dir, pending, allow_restore=False)
    _fit(_new_tuner(sweep_dir, callback, experiment, pending, workers, max_failures, checkpoint_every_s))


class _InterruptMark:
    """SIGINT handler while Tune runs, until Tune installs its own: Tune puts the previous handler back
    when (and only when) a SIGINT (or SIGTERM, ledger.sigterm_as_interrupt) made it stop, so finding
    this mark back after fit() means that Tune stopped early, saved its state and returned."""

    asp_interrupt = True  # ledger._sigterm: raise, do not call

    def __init__(self, previous):
        self.previous = previous

    def __call__(self, signum, frame):
        if callable(self.previous):
            return self.previous(signum, frame)
        if self.previous != signal.SIG_IGN:
            raise KeyboardInterrupt


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


def _restored_tuner(sweep_dir: AnyPath, experiment: str) -> tune.Tuner:
    # Restores the stored Tune settings too (max_failures, checkpoint interval, callbacks).
    storage_path, storage_fs = _tune_storage(sweep_dir)
    return tune.Tuner.restore(f"{storage_path}/{experiment}", trainable=_trainable(), resume_unfinished=True,
                              resume_errored=True, storage_filesystem=storage_fs)


def _new_tuner(sweep_dir: AnyPath, callback: SweepCallback, experiment: str, pending: list[Unit], workers: int,
               max_failures: int, checkpoint_every_s: float) -> tune.Tuner:
    configs = [unit_config(u, sweep_dir, callback.name, checkpoint_every_s) for u in pending]
    storage_path, storage_fs = _tune_storage(sweep_dir)
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
            callbacks=[callback], stop=DiskFullStopper(),
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

    with ledger.sigterm_as_interrupt(), _disk_full_is_one_line(sweep_dir, name, results):
        if address:  # a cluster that does not answer is refused before anything is written
            ledger.check_sweep_dir_readonly(sweep_dir)
            resolve_packing(pack, pack_size, store.read_manifest(sweep_dir))
            ledger.check_address(address, connect_timeout_s)
        # A cluster is joined before the sweep dir is written; the embedded Ray starts only if a cell is pending.
        with session() if address else nullcontext():
            ledger.check_sweep_dir(sweep_dir)
            with ledger.sweep_lock(sweep_dir, connect_timeout_s=connect_timeout_s):
                packing = resolve_packing(pack, pack_size, store.read_manifest(sweep_dir))  # refuses another one
                manifest = ledger.check_manifest(sweep_dir, name, specs, space, packing)  # refuses a different grid
                if store.read_manifest(sweep_dir) is None:
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
                pending = [u for u in units if not set(u.cell_ids) <= done]
                counter = SweepCounter(name, grid, done, stream=stream, where=str(store.cells_dir(sweep_dir)))
                where = f"cluster {address}" if address else f"embedded Ray, {workers} worker(s)"
                how = f", packed ({packing.describe()}: {describe_units(units)})" if packing.packed else ""
                stream.write(f"sweep {name}: space {space}, {len(specs)} cells ({len(done)} already done){how}, "
                             f"{where}, results in {sweep_dir}\n")
                if pending:
                    callback = SweepCallback(str(sweep_dir), name, grid, counter)
                    _DISK_FULL.clear()
                    with nullcontext() if address else session():
                        _run_tune(sweep_dir, callback, pending, workers, max_failures, checkpoint_every_s)
                    if _DISK_FULL:
                        raise OSError(errno.ENOSPC, "No space left on device", _DISK_FULL[0] or str(sweep_dir))
                done, failed = ledger.finished_and_failed(sweep_dir, grid, remember=True)
                counter.update(done=done, failed=failed, running=set(), last_failure=last_failure(sweep_dir, failed))
                counter.finish()
                return SweepResult(name, sweep_dir, len(specs), len(done), len(failed))
