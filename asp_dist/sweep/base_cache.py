"""Content-addressed cache of base models shared by every cell of a sweep.

One file per ``CellSpec.base_key`` (``<cache_dir>/<base_key>.pt``). The first cell that needs a
base trains it while holding an exclusive ``fcntl`` lock on ``.<base_key>.lock``; a second cell
asking at the same time blocks on the lock, then finds the file and loads it. The file appears
through an atomic rename, so a reader never sees half a base, and a crash while training leaves
only a stale temp file (the lock dies with its process). Works on one machine and on a shared
filesystem with POSIX locks (local disk, NFSv4).

A base that no attempt could train to the domain's bar is remembered too, as
``<base_key>.rejected.json``: every other cell of that trial then fails at once with the same
BaseRejected message instead of repeating all attempts (21 cells x 5 attempts for one
particle trial). Delete the file, or change base_train_steps / base_max_attempts (a new
base_key), to try again.
"""

from __future__ import annotations

import fcntl
import json
from pathlib import Path

from asp_dist.domains.contract import ProgressFn
from asp_dist.fsutil import atomic_write
from asp_dist.spec import CellSpec
from asp_dist.training.bases import BaseModel, BaseRejected, base_from_bytes, base_to_bytes, train_accepted_base


def base_path(cache_dir: Path, base_key: str) -> Path:
    return Path(cache_dir) / f"{base_key}.pt"


def rejected_path(cache_dir: Path, base_key: str) -> Path:
    return Path(cache_dir) / f"{base_key}.rejected.json"


def _raise_if_rejected(cache_dir: Path, base_key: str) -> None:
    path = rejected_path(cache_dir, base_key)
    if path.exists():
        raise BaseRejected(json.loads(path.read_text())["error"] + f" [remembered in {path}]")


def _load(path: Path, spec: CellSpec) -> BaseModel:
    base = base_from_bytes(path.read_bytes())
    if base.key != spec.base_key:
        raise ValueError(f"base cache file {path} holds base {base.key}, expected {spec.base_key}")
    return base


def get_base(spec: CellSpec, cache_dir: Path, progress: ProgressFn | None = None) -> tuple[BaseModel, bool]:
    """The cell's base: loaded from the cache, or trained once and stored. Returns (base, was_cached)."""
    spec = spec.resolved()
    cache_dir = Path(cache_dir)
    path = base_path(cache_dir, spec.base_key)
    if path.exists():
        return _load(path, spec), True
    _raise_if_rejected(cache_dir, spec.base_key)
    cache_dir.mkdir(parents=True, exist_ok=True)
    with open(cache_dir / f".{spec.base_key}.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # waits while another cell trains this base
        try:
            if path.exists():
                return _load(path, spec), True
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

