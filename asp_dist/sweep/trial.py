"""The one Tune trial function: a unit of the sweep (one cell, or a pack of cells) trained and written.

What a worker does with a unit (asp_dist.sweep.packing.Unit, as ``unit_config`` hands it to Tune):

1. skip it if every member already has a row (finished before Tune's state caught up);
2. continue from the unit's newest checkpoint when it has one (a restarted trial's, or one an earlier run of
   the sweep left) and it is of these cells;
3. get each member's base from the sweep's shared cache (asp_dist.sweep.base_cache); a base that never
   meets its bar fails that base's members only;
4. train the live members through the one cell pipeline (asp_dist.training.pipeline: a lone cell on its
   lone trainer, a pack on its domain's packed trainer), checkpointing through ``tune.report``;
5. write each member without a row as a cell (curve, then its end to the trackers, then its row), and
   record each failed member once.

A base-only unit (a packed sweep's bases, handed out first: asp_dist.sweep.packing.bases_first) only trains its
base into the sweep's cache (train_base).

A pack trains whole even when some members already have a row (so that every member's row is the one an
uninterrupted run writes); only members without a row are written. A deterministic failure (a bad spec, a
base that never meets its bar, missing or corrupt data, a member whose training diverged) is recorded under
``failed/`` and not retried: a retry would fail the same way; ``resume`` tries it again. Object storage
that does not answer is a crash, retried from the last checkpoint. A full disk is not a crash to retry: the
trial reports it (``disk_full``) and the driver stops the sweep; whatever was being written is a temp file
that is removed, never a file that counts.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable

import ray
from ray import tune

from asp_dist.data.mnist import MNISTError
from asp_dist.errors import SpecError, StorageError, is_disk_full
from asp_dist.results import store
from asp_dist.results.location import AnyPath, as_path
from asp_dist.results.s3 import S3Path
from asp_dist.spec import FIELD_NAMES, CellSpec
from asp_dist.sweep import worker_start
from asp_dist.sweep.packing import Unit
from asp_dist.sweep.tune_storage import TUNE_DIR
from asp_dist.tracking.hub import Feed, final_metrics, hub_name

# torch and the training pipeline are imported by the functions a worker runs, not here: the driver imports
# this module only to hand train_cell to Tune and to name trials, and would pay ~2 s of CPU per sweep for them.

# A worker imports this module when it unpickles train_cell, before Tune's trainable starts (no IPython import).
worker_start.skip_ipython_import()

CKPT_TMP = ".ckpt-tmp"  # under TUNE_DIR: checkpoints being written, before Tune copies them into its trial dir
DISK_FULL = "disk_full"  # a trial's result key: where a write found no space left


def deterministic_failures() -> tuple[type[Exception], ...]:
    """Failures a retry would meet again: recorded once, the sweep goes on."""
    from asp_dist.training.bases import BaseRejected

    return SpecError, BaseRejected, MNISTError


def unit_config(unit: Unit, sweep_dir: AnyPath, sweep_id: str, checkpoint_every_s: float) -> dict[str, Any]:
    """What a Tune trial gets for a unit: its name (the cell id, or the pack's name), pack id (None for a
    single cell), members' specs and cell ids, and where the sweep writes."""
    return {"name": unit.name, "pack_id": unit.pack_id, "specs": [s.to_dict() for s in unit.specs],
            "cell_ids": unit.cell_ids, "sweep_dir": str(sweep_dir), "sweep_id": sweep_id,
            "checkpoint_every_s": checkpoint_every_s, "base_only": unit.base_only}


def unit_from_config(config: dict[str, Any]) -> dict[str, Any]:
    """A trial's config in today's shape. A single cell's config of older code (a restored experiment) had
    "spec" and "cell_id" instead of a one-member list."""
    if "spec" in config:
        config = {k: v for k, v in config.items() if k not in ("spec", "cell_id")} | {
            "name": config["cell_id"], "pack_id": None, "specs": [config["spec"]], "cell_ids": [config["cell_id"]]}
    return config


def config_cells(config: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(cell id, domain, method) of every cell a trial's config runs."""
    config = unit_from_config(config)
    return [(cid, s["domain"], s["method"]) for cid, s in zip(config["cell_ids"], config["specs"])]


def trial_name(trial) -> str:
    """A trial's name and directory are its unit's name: the cell id, or the pack's name (a worker's
    working directory ends with it)."""
    return unit_from_config(trial.config["cell"])["name"]


def train_cell(config: dict[str, Any]) -> None:
    """The function trainable of every sweep. Keeps no state between calls: actors are reused across units."""
    import torch

    torch.set_num_threads(1)
    unit = unit_from_config(config["cell"])
    try:
        if unit.get("base_only"):
            train_base(unit)
        else:
            train_unit(unit)
    except OSError as e:
        if not is_disk_full(e):
            raise
        tune.report({"cell_done": 0, DISK_FULL: getattr(e, "filename", None) or unit["sweep_dir"]})


def train_base(unit: dict[str, Any]) -> None:
    """A base-only unit (asp_dist.sweep.packing.bases_first): its spec's base trained into the sweep's cache, or
    loaded if another worker stored it meanwhile. A base that meets no bar is remembered there as rejected
    (base_cache), and its cells fail at once with that message when their units run: nothing is recorded here."""
    from asp_dist.sweep.base_cache import get_base

    spec = CellSpec.from_dict(unit["specs"][0]).resolved()
    try:
        _, cached = get_base(spec, store.bases_dir(as_path(unit["sweep_dir"])))
    except StorageError:
        raise
    except deterministic_failures():
        tune.report({"cell_done": 0, "base_done": 0})
        return
    tune.report({"cell_done": 0, "base_done": 1, "skipped": int(cached)})


def train_unit(unit: dict[str, Any], report: Callable[..., None] | None = None,
               on_points: Callable[[Any], None] | None = None) -> None:
    """Train one unit's members without a row and write them (the module docstring's steps). `report`: what
    the unit's results and checkpoints go through (tune.report; asp-dist tune adds its objective to each);
    `on_points`: also given the members' curve points as they close, beside the tracker feed (asp-dist tune's
    early stopping reads them)."""
    report = report or tune.report
    from asp_dist.sweep.base_cache import get_base
    from asp_dist.training import engines
    from asp_dist.training.pipeline import run_unit, upgrade_checkpoint

    deterministic = deterministic_failures()
    specs = [CellSpec.from_dict(d).resolved() for d in unit["specs"]]
    sweep_dir, pack_id = as_path(unit["sweep_dir"]), unit["pack_id"]
    todo = {s.cell_id for s in specs if not store.is_done(sweep_dir, s.domain, s.method, s.cell_id)}
    if not todo:
        report({"cell_done": 1, "skipped": 1})  # finished before Tune's state caught up
        return
    failures: dict[str, str] = {}
    bases: dict[str, Any] = {}
    for spec in specs:  # one base per key from the sweep's cache
        if spec.base_key in bases or spec.cell_id in failures:
            continue
        try:
            bases[spec.base_key], _ = get_base(spec, store.bases_dir(sweep_dir))
        except StorageError:
            raise
        except deterministic as e:
            why = f"{type(e).__name__}: {e}"
            failures.update({s.cell_id: why for s in specs if s.base_key == spec.base_key})
    live = [s for s in specs if s.cell_id not in failures]
    feed = _feed(unit["sweep_id"], todo)
    restore = _restored_state(sweep_dir, unit["name"])
    if restore is not None:
        restore = upgrade_checkpoint(restore)
        if (restore.get("pack_id"), restore.get("cell_ids")) != (pack_id, [s.cell_id for s in live]):
            restore = None  # another composition (a base was rejected or accepted since): start over
    save = _checkpointer(sweep_dir, unit["name"], report)
    results = []
    if live:
        trainer = engines.lone_trainer(live[0]) if pack_id is None else engines.pack_trainer(live[0])
        try:
            results = run_unit(trainer, live, bases=bases, curves=True,
                               checkpoint=lambda state: save(dict(state, pack_id=pack_id)), restore=restore,
                               checkpoint_every_s=unit["checkpoint_every_s"], on_points=_both(feed, on_points))
        except StorageError:
            raise
        except deterministic as e:
            failures.update({s.cell_id: f"{type(e).__name__}: {e}" for s in live})
    written, finals = 0, {}
    for result in results:
        spec = result.spec
        if spec.cell_id not in todo:
            continue  # a row written before (e.g. by the interrupted run of this pack): never rewritten
        if result.row is None:
            why = f"{type(result.exception).__name__}: {result.error}"
            failures[spec.cell_id] = why if pack_id is None else f"in pack {pack_id}: {why}"
            continue
        row = dict(result.row, ray_node_id=ray.get_runtime_context().get_node_id(), ray_version=ray.__version__)
        if pack_id is not None:
            row["pack"] = pack_id
        store.write_curve(sweep_dir, row, result.curve or [])
        finals[spec.cell_id] = final_metrics(row, FIELD_NAMES)
        if feed is not None:  # before the row: a cell with a row is never run again to resend its end
            _finish(feed, unit["sweep_id"], spec.cell_id, finals[spec.cell_id], spec.train_steps)
        written += store.write_row(sweep_dir, row, unit["sweep_id"])
        store.clear_failure(sweep_dir, spec.cell_id)
    for spec in specs:
        if spec.cell_id in failures and spec.cell_id in todo:
            if feed is not None:
                _finish(feed, unit["sweep_id"], spec.cell_id, {}, 0, failures[spec.cell_id])
            store.record_failure(sweep_dir, spec.cell_id, spec.domain, spec.method, failures[spec.cell_id])
    report(final_report(unit, finals, written, failures))


def final_report(unit: dict[str, Any], finals: dict[str, dict[str, float]], written: int,
                 failures: dict[str, str]) -> dict[str, Any]:
    """A trial's last result, as Tune's readers show it (ExperimentAnalysis, ResultGrid.get_dataframe(): one
    row per trial): its cell ids and each written cell's final eval_* metrics -- a lone cell's at the top,
    a pack's members' under members/<cell id>/ (Tune's dataframe flattens them to columns). The Parquet rows
    remain the truth; this is a view for Tune's tools."""
    report: dict[str, Any] = {"cell_done": int(not failures), "cells_written": written, "cell_failed": len(failures),
                              "cell_ids": ",".join(unit["cell_ids"]), "pack_id": unit["pack_id"] or ""}
    if unit["pack_id"] is None:
        report.update(next(iter(finals.values()), {}))
    else:
        report["members"] = finals
    return report


_HUBS: dict[str, Any] = {}  # sweep -> its hub's handle (or None), looked up once per worker process and Ray session
_SILENT_HUBS: set[str] = set()  # sweeps whose hub once left a cell's end unanswered: not waited for again here


def _both(first: Callable[[Any], None] | None, second: Callable[[Any], None] | None) -> Callable[[Any], None] | None:
    """One on_points hook calling each of two (either may be None)."""
    hooks = [h for h in (first, second) if h is not None]
    if len(hooks) < 2:
        return hooks[0] if hooks else None

    def both(batch: Any) -> None:
        for hook in hooks:
            hook(batch)
    return both


def _feed(sweep: str, cells: set[str]) -> Feed | None:
    """The feed to the sweep's tracker hub (asp_dist.tracking.hub), for `cells` only (a pack's members with
    a row are done in their trackers too); None when the sweep runs without trackers. (A worker lives in one
    Ray session, and a session runs one sweep run: its hub, or none, for every trial the worker takes.)"""
    if sweep not in _HUBS:
        if not ray.is_initialized():  # train_cell called outside Ray: no hub, and get_actor would start a Ray
            return None
        try:
            _HUBS[sweep] = ray.get_actor(hub_name(sweep))
        except ValueError:
            _HUBS[sweep] = None
    if _HUBS[sweep] is None:
        return None
    return Feed(_HUBS[sweep], only=cells, wait=None if sweep in _SILENT_HUBS else _answered)


def _finish(feed: Feed, sweep: str, cell_id: str, final: dict[str, float], step: int, error: str | None = None) -> None:
    """The cell's end to its trackers, waited for (see Feed.finish); a hub that leaves it unanswered is not
    waited for again by this worker process."""
    if not feed.finish(cell_id, final, step, error):
        _SILENT_HUBS.add(sweep)


def _answered(ref: Any, seconds: float) -> bool:
    """Whether an actor call has answered within `seconds` (a hub that died answers with an error: no)."""
    ready, _ = ray.wait([ref], timeout=seconds)
    if not ready:
        return False
    try:
        ray.get(ready[0])
    except ray.exceptions.RayError:
        return False
    return True


def _restored_state(sweep_dir: AnyPath, name: str) -> dict | None:
    """The state of the unit's newest checkpoint, else None: the one Tune hands a restarted trial (a worker that
    died), or else the newest the unit left in an earlier experiment of the sweep (a resumed sweep starts a new
    experiment: asp_dist.sweep.tune never restores Tune's own pickled state).

    A checkpoint Tune names may be gone (Tune deletes the older one as soon as a newer one is registered, and
    on S3 uploads asynchronously); one may be cut short or planted. Each is read with weights_only
    (asp_dist.training.artefacts): one that cannot be read is named in one warning line, never unpickled, and
    the next older one is tried; with none left the cell starts over (its row is the same, only time is lost)."""
    checkpoint = tune.get_checkpoint()
    if checkpoint is not None:
        try:
            with checkpoint.as_directory() as d:
                state, problem = _read_state(Path(d) / "state.pt", f"checkpoint {checkpoint.path}/state.pt")
        except FileNotFoundError:  # nothing at all under the checkpoint's path
            state, problem = None, None
        if state is None:
            problem = problem or (f"the checkpoint {checkpoint.path} Tune restores this trial from holds no state "
                                  f"(deleted after a newer one while Tune's experiment state was on its way to "
                                  f"storage)")
            print(f"asp-dist: warning: {problem}; the trial starts over", file=sys.stderr, flush=True)
        return state
    for path in _earlier_checkpoints(sweep_dir, name):
        state, problem = _read_state(path, f"checkpoint {path}")
        if state is not None:
            return state
        if problem is not None:
            print(f"asp-dist: warning: {problem}; not restored from it", file=sys.stderr, flush=True)
    return None


def _read_state(path: AnyPath, what: str) -> tuple[dict | None, str | None]:
    """(a checkpoint's state, None), or (None, what is wrong with the file), or (None, None) when there is none."""
    from asp_dist.training.artefacts import DamagedArtefact, load_file

    try:
        state = load_file(path, what)
    except FileNotFoundError:
        return None, None
    except DamagedArtefact as err:
        return None, str(err)
    return (state, None) if isinstance(state, dict) else (None, f"{what} holds no checkpoint's state")


def _earlier_checkpoints(sweep_dir: AnyPath, name: str) -> list[AnyPath]:
    """state.pt of every checkpoint the unit `name` left under the sweep's Tune experiments
    (tune/run-<n>/<name>/checkpoint_<k>/), newest first (by n, then k)."""
    found = []
    for run in numbered_entries(sweep_dir / TUNE_DIR, "run-"):
        for checkpoint in numbered_entries(run[1] / name, "checkpoint_"):
            found.append(((run[0], checkpoint[0]), checkpoint[1] / "state.pt"))
    return [path for _, path in sorted(found, key=lambda item: item[0], reverse=True)]


def numbered_entries(directory: AnyPath, prefix: str) -> list[tuple[int, AnyPath]]:
    """(n, path) of the entries <prefix><n> of a local or S3 directory; none when it does not exist."""
    try:
        entries = list(directory.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return []
    return [(int(p.name[len(prefix):]), p) for p in entries
            if p.name.startswith(prefix) and p.name[len(prefix):].isdigit()]


def _checkpointer(sweep_dir: AnyPath, name: str, report: Callable[..., None]):
    """save(state): one checkpoint of the trial through `report` (tune.report)."""
    # On S3 the sweep has no local directory: stage in the trial's working directory, which Tune keeps
    # under the Ray temp dir (node-local scratch, pruned with its session).
    from asp_dist.training.artefacts import to_bytes

    staging = Path.cwd() / CKPT_TMP if isinstance(sweep_dir, S3Path) else sweep_dir / TUNE_DIR / CKPT_TMP

    def save(state: dict) -> None:
        # Staged in the sweep's own tree (never the system temp dir: it may be small, shared or wiped),
        # written under a temp name and renamed, and removed once report() returns: Tune has copied
        # it into the trial's storage by then.
        staging.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f"{name}-", dir=staging) as d:
            part = Path(d) / ".state.pt.part"
            part.write_bytes(to_bytes(state))  # plain containers of tensors: read back with weights_only
            os.replace(part, Path(d) / "state.pt")
            report({"cell_done": 0, "step": state["trainer"]["step"]}, checkpoint=tune.Checkpoint.from_directory(d))

    return save
