"""Content-addressed cache of base models shared by every cell of a sweep.

One file per ``CellSpec.base_key`` (``<cache_dir>/<base_key>.pt``). The first cell that needs a
base trains it while holding an exclusive ``fcntl`` lock on ``.<base_key>.lock``; a second cell
asking at the same time blocks on the lock, then finds the file and loads it. The file appears
through an atomic rename, so a reader never sees half a base, and a crash while training leaves
only a stale temp file (the lock dies with its process). Works on one machine and on a shared
filesystem with POSIX locks (local disk, NFSv4).

On S3 (``cache_dir`` an asp_dist.results.s3.S3Path) there are no fcntl locks: the first cell
that needs a base takes a lease ``bases/.<base_key>.lease/`` (asp_dist.sweep.lease: a conditional
PUT, renewed while it trains; it lapses if the worker dies) and stores the base with a conditional
PUT (``If-None-Match: *``); cells asking meanwhile poll for the object and load it. Should two
workers still both train one base (a builder silent for longer than the lease lasts), the first PUT
wins and the other cell loads the stored base instead of its own: every cell of a trial uses the
same bytes, and a stored base is never overwritten.

A base file that cannot be read safely (truncated, planted, of an older format: asp_dist.training.artefacts)
is refused in one warning line, moved to ``<sweep>/damaged/<UTC time>/bases/`` as a damaged cell file is, and
trained again, under the same lock or lease as a first training; it is never unpickled.

A base that no attempt could train to the domain's bar is remembered too, as
``<base_key>.rejected.json``: every other cell of that trial then fails at once with the same
BaseRejected message instead of repeating all attempts (21 cells x 5 attempts for one
particle trial). Delete the file, or change base_train_steps / base_max_attempts (a new
base_key), to try again.
"""

from __future__ import annotations

import fcntl
import json
import sys
import time
from pathlib import Path

from asp_dist.core.contract import ProgressFn
from asp_dist.fsutil import atomic_write
from asp_dist.results import store
from asp_dist.results.location import AnyPath, move_aside, write_replace
from asp_dist.results.s3 import S3Path
from asp_dist.spec import CellSpec
from asp_dist.training.artefacts import DamagedArtefact
from asp_dist.training.bases import BaseModel, BaseRejected, base_from_bytes, base_to_bytes, train_accepted_base

POLL_S = 1.0  # on S3: how often a cell waiting for a base being trained elsewhere looks for it


base_path, rejected_path = store.base_path, store.rejected_base_path  # the file names, torch-free for the driver


def _raise_if_rejected(cache_dir: AnyPath, base_key: str) -> None:
    path = rejected_path(cache_dir, base_key)
    if not path.exists():
        return
    try:
        error = json.loads(path.read_text())["error"]
    except (ValueError, UnicodeDecodeError, KeyError, TypeError):  # not what this module writes: no verdict
        return
    raise BaseRejected(f"{error} [remembered in {path}]")


def _load(path: AnyPath, spec: CellSpec) -> BaseModel:
    """The stored base (FileNotFoundError when there is none; DamagedArtefact when it cannot be read)."""
    return base_from_bytes(path.read_bytes(), spec, what=f"base file {path}")


def _stored(path: AnyPath, spec: CellSpec) -> BaseModel | None:
    """The stored base, or None when there is none or it was damaged: then it is set aside (the caller holds the
    base's lock or lease, so no other cell is reading it as it moves) and the caller trains it again."""
    try:
        return _load(path, spec)
    except FileNotFoundError:
        return None
    except DamagedArtefact as err:
        _set_aside(path, str(err))
        return None


def _set_aside(path: AnyPath, problem: str) -> None:
    """Move a damaged base file to <sweep>/damaged/<UTC time>/bases/, kept for inspection, never read again."""
    dest = store.damaged_dest(path.parent.parent, store.damaged_stamp(), path)  # <sweep>/bases/<key>.pt
    try:
        move_aside(path, dest)
    except FileNotFoundError:  # set aside by another cell meanwhile
        return
    print(f"asp-dist: warning: {problem}; moved to {dest} and trained again", file=sys.stderr, flush=True)


def _get_remote_base(spec: CellSpec, cache_dir: S3Path, progress: ProgressFn | None) -> tuple[BaseModel, bool]:
    from asp_dist.sweep.lease import Lease

    path = base_path(cache_dir, spec.base_key)
    while True:
        try:
            return _load(path, spec), True
        except (FileNotFoundError, DamagedArtefact):  # none yet, or one to set aside under the lease
            pass
        _raise_if_rejected(cache_dir, spec.base_key)
        lease = Lease(cache_dir / f".{spec.base_key}.lease")
        if lease.try_acquire() is not None:
            time.sleep(POLL_S)  # another cell trains it: wait for its object
            continue
        try:
            stored = _stored(path, spec)
            if stored is not None:
                return stored, True
            _raise_if_rejected(cache_dir, spec.base_key)  # decided while we waited
            try:
                base = train_accepted_base(spec, progress)
            except BaseRejected as err:
                write_replace(rejected_path(cache_dir, spec.base_key), json.dumps({"error": str(err)}))
                raise
            if path.create(base_to_bytes(base)):
                return base, False
            return _load(path, spec), True  # stored by another cell meanwhile: every cell uses the stored bytes
        finally:
            lease.release()


def get_base(spec: CellSpec, cache_dir: AnyPath, progress: ProgressFn | None = None) -> tuple[BaseModel, bool]:
    """The cell's base: loaded from the cache, or trained once and stored. Returns (base, was_cached)."""
    spec = spec.resolved()
    if isinstance(cache_dir, S3Path):
        return _get_remote_base(spec, cache_dir, progress)
    cache_dir = Path(cache_dir)
    path = base_path(cache_dir, spec.base_key)
    try:
        return _load(path, spec), True
    except (FileNotFoundError, DamagedArtefact):  # none yet, or one to set aside under the lock
        pass
    _raise_if_rejected(cache_dir, spec.base_key)
    cache_dir.mkdir(parents=True, exist_ok=True)
    with open(cache_dir / f".{spec.base_key}.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # waits while another cell trains this base
        try:
            stored = _stored(path, spec)
            if stored is not None:
                return stored, True
            _raise_if_rejected(cache_dir, spec.base_key)  # decided while we waited for the lock
            try:
                base = train_accepted_base(spec, progress)
            except BaseRejected as err:
                atomic_write(rejected_path(cache_dir, spec.base_key), json.dumps({"error": str(err)}))
                raise
            atomic_write(path, base_to_bytes(base))
            return base, False
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)

