"""The ledger of a sweep: its name and directory, its lock, its grid (manifest) and its status.

What a sweep records around running cells, and nothing that runs them: no Ray import, so `asp-dist status`
and its tests are fast and need no cluster. The checks made before a run (directories, options, the
cluster address, the grid) are asp_dist.sweep.preflight; SIGTERM as Ctrl-C is asp_dist.sweep.signals.
The files themselves (manifest, finished cells, failures) are laid out by asp_dist.results.store;
this module decides what they must say for a sweep to start, continue or be reported.

A sweep under ``--results s3://bucket/prefix`` is the same ledger on object storage: its directory
is an S3Path (asp_dist.results.s3), and its lock is a lease (asp_dist.sweep.lease) instead
of an fcntl lock, which object storage does not have.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import socket
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, Iterable, Iterator

from asp_dist import __version__
from asp_dist.core.registry import DOMAINS
from asp_dist.errors import SpecError, SweepError
from asp_dist.method_registry import METHODS, split_arm
from asp_dist.results import store
from asp_dist.results.location import AnyPath, as_path, is_remote
from asp_dist.results.s3 import S3Path, check_bucket
from asp_dist.spec import CellSpec
from asp_dist.sweep.packing import MANIFEST_KEY, Packing, make_units, stored_packing
from asp_dist.sweep.spaces import grid_hash

SWEEP_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")  # a directory name, never a path
LOCK_FILE = ".lock"
# How long a starting run retries the lock before calling the sweep busy: `status` probes it with a
# shared lock held for microseconds, and a probe must never make a starting run refuse.
LOCK_GRACE_S = 2.0
DEFAULT_CONNECT_TIMEOUT_S = 20.0


@dataclass
class SweepResult:
    """Where a sweep run left its grid."""

    name: str
    sweep_dir: AnyPath
    total: int
    done: int
    failed: int

    @property
    def pending(self) -> int:
        return self.total - self.done - self.failed


# ---- name and directory --------------------------------------------------------------------------
def sweep_dir_for(results: str | AnyPath, name: str) -> AnyPath:
    """``<results>/<name>``, absolute; refuses a name that is not a plain directory name. For
    ``s3://bucket/prefix`` the bucket is checked (endpoint, credentials, bucket: one line each)."""
    if not SWEEP_NAME_RE.match(name):
        raise SweepError(f"invalid sweep name {name!r}: use letters, digits, '.', '_' or '-' (at most 64)")
    if is_remote(results):
        root = as_path(str(results))
        check_bucket(root)
        return root / name
    return Path(results).expanduser().resolve() / name


# ---- lock ----------------------------------------------------------------------------------------
LEASE_DIR = ".lease"  # on S3: <sweep>/.lease/<generation>.json (asp_dist.sweep.lease)


def _sweep_lease(sweep_dir: S3Path):
    from asp_dist.sweep.lease import Lease

    def lost(why: str) -> None:  # another run took the sweep over: stop this one as Ctrl-C would
        print(f"asp-dist: error: {why}; stopping this run", file=sys.stderr)
        os.kill(os.getpid(), signal.SIGTERM)

    return Lease(sweep_dir / LEASE_DIR, on_lost=lost)


def lease_wait_bound_s(connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S) -> float:
    """How long a run waits for a silent lease to lapse: as long as a lease asp-dist writes can outlive its
    holder (LEASE_TTL_S), or the connect timeout if that is longer. A lease that says it lasts longer
    (a planted or foreign ttl_s) is refused at once, with whose it is and until when, never waited for."""
    from asp_dist.sweep.lease import LEASE_TTL_S

    return max(float(connect_timeout_s), LEASE_TTL_S + 2.0)


@contextmanager
def _remote_sweep_lock(sweep_dir: S3Path, grace_s: float,
                       connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S) -> Iterator[None]:
    lease = _sweep_lease(sweep_dir)
    deadline = time.monotonic() + grace_s
    bound = lease_wait_bound_s(connect_timeout_s)
    told = False
    while (busy := lease.try_acquire()) is not None:
        silent = busy.age_s > 2 * lease.renew_s  # not renewed for two intervals: its driver is most likely dead
        if silent:  # (killed on another machine): wait for its lease to lapse rather than refuse
            left = float(busy.record.get("ttl_s", lease.ttl_s)) - busy.age_s
            if not told and left + 2.0 > bound:
                until = ((datetime.now(timezone.utc) + timedelta(seconds=left)).isoformat(timespec="seconds")
                         if left < 3e9 else "in a century or more")  # beyond that a date is noise
                raise SweepError(
                    f"sweep {sweep_dir.name!r} is held by {busy.record.get('holder', 'another run')}, silent for "
                    f"{busy.age_s:.0f} s, whose lease lapses only in {left:.0f} s ({until}), beyond the {bound:.0f} s "
                    f"this run waits; if that run is dead, delete {lease.prefix}/ and run again")
            deadline = max(deadline, time.monotonic() + left + 2.0)
            if not told:
                print(f"asp-dist: sweep {sweep_dir.name!r}: waiting up to {max(left, 0):.0f} s for the silent lease of "
                      f"{busy.record.get('holder', 'another run')} to lapse", file=sys.stderr)
                told = True
        if time.monotonic() >= deadline:
            raise SweepError(f"sweep {sweep_dir.name!r} is already running ({busy.describe()}); wait for it to "
                             f"finish or use another --name")
        time.sleep(1.0 if silent else 0.2)
    try:
        yield
    finally:
        lease.release()


@contextmanager
def sweep_lock(sweep_dir: AnyPath, grace_s: float = LOCK_GRACE_S,
               connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S) -> Iterator[None]:
    """Refuse a second concurrent run of one sweep. fcntl: the OS drops the lock when its holder dies,
    even by SIGKILL, so a crashed run never blocks the resume. Retried for ``grace_s`` so that a
    `status` probing the lock at that moment (lock_holder) never makes the run refuse. On S3: a lease
    (asp_dist.sweep.lease), created by a conditional PUT and renewed while the run lasts."""
    if isinstance(sweep_dir, S3Path):
        with _remote_sweep_lock(sweep_dir, grace_s, connect_timeout_s):
            yield
        return
    fh = open(sweep_dir / LOCK_FILE, "a+")
    try:
        deadline = time.monotonic() + grace_s
        while True:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() < deadline:
                    time.sleep(0.02)
                    continue
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


def lock_holder(sweep_dir: AnyPath) -> str | None:
    """Who holds the sweep's lock, or None if no run of the sweep is going on.

    Never blocks and never refuses anyone: the file is opened read-only (nothing is created or written)
    and probed with a *shared* lock, which fails only against a run's exclusive one. Two probes never
    see each other as a run, and a run starting during a probe retries (sweep_lock's grace). On S3 the
    lease is read (a listing and one GET), never written."""
    if isinstance(sweep_dir, S3Path):
        return _sweep_lease(sweep_dir).holder()
    try:
        fh = open(sweep_dir / LOCK_FILE)
    except FileNotFoundError:
        return None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return fh.read().strip() or "unknown"
        fcntl.flock(fh, fcntl.LOCK_UN)
    return None


# ---- grid (manifest) -----------------------------------------------------------------------------
def new_manifest(name: str, space: str, specs: list[CellSpec], packing: Packing | None = None) -> dict[str, Any]:
    """The manifest of a new sweep: its grid as cell ids and resolved specs, the grid's hash, how its
    cells are grouped into Tune trials (asp_dist.sweep.packing; fixed for the sweep's life), and which
    plugin (entry point, distribution, version) provides each of its domains and methods."""
    return {"name": name, "space": space, "grid_hash": grid_hash(specs), "cells": [s.cell_id for s in specs],
            "specs": [s.to_dict() for s in specs], MANIFEST_KEY: (packing or Packing()).to_dict(),
            "domains": domain_plugins(sorted({s.domain for s in specs})),
            "methods": method_plugins(sorted({s.method for s in specs})),
            "asp_dist_version": __version__, "created_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def extended_manifest(existing: dict[str, Any], space: str, specs: list[CellSpec]) -> dict[str, Any]:
    """The manifest of a sweep grown by `--extend` to the grid `specs`, or a SweepError naming what differs.

    Allowed: the new grid holds every stored cell (same ids: no value removed, no knob changed) and every
    stored cell stays in the Tune trial it had (the same pack, or alone), so finished rows, failure records,
    bases and checkpoints all stay valid; new cells make new units (a grown trial range makes new packs; new
    members of an existing trial's pack would change that pack, and are refused). The packing is the stored
    one. `history` records each grid the sweep has had: hash, space, cell count, when."""
    name = existing["name"]
    old = specs_from_manifest(existing)
    new_ids = {s.cell_id for s in specs}
    missing = [s.cell_id for s in old if s.cell_id not in new_ids]
    if missing:
        raise SweepError(f"--extend keeps every cell of sweep {name!r}, but the new grid lacks {len(missing)} of its "
                         f"{len(old)} cells (e.g. {missing[0]}: a value removed from an axis, or a knob changed); "
                         f"add cells only, or use another --name")
    packing = stored_packing(existing) or Packing()
    grown = {tuple(u.cell_ids): u.pack_id for u in make_units(specs, packing)}
    for unit in make_units(old, packing):
        if grown.get(tuple(unit.cell_ids), "changed") != unit.pack_id:
            what = f"pack {unit.pack_id}" if unit.pack_id else f"cell {unit.cell_ids[0]}"
            raise SweepError(f"--extend would change the Tune trial of {what} of sweep {name!r} ({packing.describe()}): "
                             f"new cells may not join the packs of stored ones; extend by whole trials (a new trial "
                             f"range) or use another --name")
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    history = list(existing.get("history") or [{"grid_hash": existing["grid_hash"], "space": existing["space"],
                                                "cells": len(old), "at": existing.get("created_at")}])
    history.append({"grid_hash": grid_hash(specs), "space": space, "cells": len(specs), "at": now})
    return dict(existing, space=space, grid_hash=grid_hash(specs), cells=[s.cell_id for s in specs],
                specs=[s.to_dict() for s in specs], domains=domain_plugins(sorted({s.domain for s in specs})),
                methods=method_plugins(sorted({s.method for s in specs})), history=history)


def domain_plugins(names: list[str]) -> dict[str, dict[str, str]]:
    """domain -> {entry_point, distribution, version} of the plugin that provides it (registry.DOMAINS)."""
    return _provenance(DOMAINS, names)


def method_plugins(names: list[str]) -> dict[str, dict[str, str]]:
    """method -> {entry_point, distribution, version} of the plugin that provides it (asp_dist.method_registry); an
    arm (`osp@default`) is provided by its method's plugin."""
    plugins = _provenance(METHODS, sorted({split_arm(n)[0] for n in names}))
    return {n: plugins[split_arm(n)[0]] for n in names if split_arm(n)[0] in plugins}


def _provenance(registry, names: list[str]) -> dict[str, dict[str, str]]:
    out = {}
    for name in names:
        plugin = registry.plugins.get(name)
        if plugin is not None:
            out[name] = {"entry_point": plugin.value, "distribution": plugin.distribution, "version": plugin.version}
    return out


def check_manifest_shape(manifest: dict[str, Any], where: AnyPath) -> None:
    """A manifest as new_manifest writes it: name, space and grid_hash as text, the cell ids and a resolved
    spec dict (with its domain and method) per cell. Anything else is refused in one line, never a KeyError."""
    path = where / store.MANIFEST
    for key in ("name", "space", "grid_hash"):
        if not isinstance(manifest.get(key), str):
            raise SweepError(f"{path} is not a sweep manifest: {key!r} is missing or not text")
    cells, specs = manifest.get("cells"), manifest.get("specs")
    if not isinstance(specs, list) or len(specs) != len(cells):
        raise SweepError(f"{path} is not a sweep manifest: it needs one spec under 'specs' per cell id in 'cells'")
    for spec in specs:
        if not (isinstance(spec, dict) and isinstance(spec.get("domain"), str) and isinstance(spec.get("method"), str)):
            raise SweepError(f"{path} is not a sweep manifest: every spec needs a domain and a method")


# What asp-dist tune (asp_dist.sweep.tuning) keeps in its run's directory: its plan, every configuration tried
TUNE_PLAN_FILE, TUNE_CONFIGURATIONS = "tune-plan.json", "configurations.parquet"
DECIDE_FILE = "decide.json"  # asp_dist.study.decide_run: a decided sweep's registration and looks


def read_sweep(results: str | AnyPath, name: str) -> tuple[AnyPath, dict[str, Any]]:
    """The directory and manifest of an existing sweep (for resume and status), its shape checked."""
    sweep_dir = sweep_dir_for(results, name)
    if not isinstance(sweep_dir, S3Path) and sweep_dir.exists() and not sweep_dir.is_dir():
        raise SweepError(f"{sweep_dir} is not a sweep directory")
    manifest = store.read_manifest(sweep_dir)
    if manifest is None:
        if (sweep_dir / TUNE_PLAN_FILE).exists():  # asp_dist.sweep.tuning's record: a tune run has no fixed grid
            raise SweepError(f"{name} is a tune run (asp-dist tune), not a sweep: its configurations are in "
                             f"{sweep_dir / TUNE_CONFIGURATIONS}; continue it with the same `asp-dist tune` "
                             f"command; `asp-dist query {name}` and `asp-dist stats {name}` read its cells")
        raise SweepError(f"no sweep {name!r} under {sweep_dir.parent}; start it with "
                         f"`asp-dist sweep SPACE --name {name}`")
    check_manifest_shape(manifest, sweep_dir)
    return sweep_dir, manifest


def specs_from_manifest(manifest: dict[str, Any]) -> list[CellSpec]:
    """The grid's specs, checked to resolve to the ids they were stored under."""
    try:
        specs = [CellSpec.from_dict(d).resolved() for d in manifest["specs"]]
    except (KeyError, TypeError, SpecError) as e:
        raise SweepError(f"sweep {manifest.get('name')!r}: its manifest's specs cannot be read ({e}); "
                         f"start a new sweep name") from None
    if [s.cell_id for s in specs] != manifest["cells"]:
        raise SweepError(f"sweep {manifest['name']!r}: its cells no longer resolve to the stored ids "
                         f"(CellSpec or domain defaults changed); start a new sweep name")
    return specs


def finished_and_failed(sweep_dir: AnyPath, grid: Iterable[str], remember: bool = False) -> tuple[set[str], set[str]]:
    """Cells of the grid with a row, and cells recorded as failed that have no row (a retry may have won).
    `remember`: the driver keeps its verdicts in the sweep's verdict index (store.cell_files)."""
    grid = set(grid)
    done = store.done_cell_ids(sweep_dir, remember=remember) & grid
    failed = (set(store.failed_cells(sweep_dir)) & grid) - done
    return done, failed


# ---- status --------------------------------------------------------------------------------------
def sweep_status(name: str, results: str | AnyPath = store.DEFAULT_RESULTS, list_failed: bool = False) -> str:
    """Done / failed / pending counts per domain and method, whether a run is going on, and the failures
    grouped by cause (`list_failed`: every failed cell with its error instead)."""
    sweep_dir, manifest = read_sweep(results, name)
    done, failed = finished_and_failed(sweep_dir, manifest["cells"])
    failures = store.failed_cells(sweep_dir) if failed else {}
    specs = dict(zip(manifest["cells"], manifest["specs"]))
    table: dict[tuple[str, str], list[int]] = {}
    for cell_id, spec in specs.items():
        counts = table.setdefault((spec["domain"], spec["method"]), [0, 0, 0])
        counts[0 if cell_id in done else 1 if cell_id in failed else 2] += 1
    holder = lock_holder(sweep_dir)
    wd = max([12, *(len(d) + 2 for d, _ in table)])  # columns as wide as the longest name
    wm = max([8, *(len(m) + 2 for _, m in table)])
    lines = [f"sweep {name}: space {manifest['space']}, {len(manifest['cells'])} cells, grid {manifest['grid_hash']}, "
             + (f"RUNNING ({holder})" if holder else "not running"),
             f"{'domain':<{wd}}{'method':<{wm}}{'done':>7}{'failed':>8}{'pending':>9}"]
    totals = [0, 0, 0]
    for (domain, method), (d, f, p) in sorted(table.items()):
        lines.append(f"{domain:<{wd}}{method:<{wm}}{d:>7}{f:>8}{p:>9}")
        totals = [totals[0] + d, totals[1] + f, totals[2] + p]
    lines.append(f"{'total':<{wd + wm}}{totals[0]:>7}{totals[1]:>8}{totals[2]:>9}")
    if list_failed:
        lines += [f"failed {cell_id}: {store.last_error_line(failures[cell_id])}" for cell_id in sorted(failed)]
    elif failed:
        causes = failure_causes(failed, failures, specs)
        lines.append(f"failed: {len(failed)} cell{'s' * (len(failed) != 1)}, {len(causes)} "
                     f"cause{'s' * (len(causes) != 1)} (asp-dist status {name} --failed lists each cell)")
        lines += [f"  {cause}" for cause in causes]
    return "\n".join(lines)


_NUMBERS = re.compile(r"\[[^\]]*\]|\d+(?:\.\d+)?")


def failure_causes(failed: Iterable[str], records: dict[str, dict[str, Any]], specs: dict[str, dict[str, Any]]) -> list[str]:
    """One line per cause of the `failed` cells, the most cells first. A base that met no bar is a trial's
    cause, shared by all its cells: "2 particles trials found no base in 10 attempts: 2089, 2166 — 18 cells".
    Other errors are grouped by their last line with numbers and bracketed lists set aside (a divergence at
    update 812 and one at 3,004 are one cause), each shown by its first cell's error."""
    groups: dict[tuple, list[str]] = {}
    for cell_id in sorted(failed):
        line = store.last_error_line(records.get(cell_id, {}), width=100_000)
        spec = specs.get(cell_id, {})
        if store.is_base_rejection(records.get(cell_id, {})):
            key: tuple = ("base", str(spec.get("domain")), spec.get("base_max_attempts"))
        else:
            key = ("error", _NUMBERS.sub("#", line))
        groups.setdefault(key, []).append(cell_id)
    out = []
    for key, cells in sorted(groups.items(), key=lambda kv: (-len(kv[1]), kv[0])):
        n = f"{len(cells)} cell{'s' * (len(cells) != 1)}"
        if key[0] == "base":
            trials = sorted({specs[c]["trial"] for c in cells})
            attempts = f" in {key[2]} attempts" if key[2] is not None else ""
            out.append(f"{len(trials)} {key[1]} trial{'s' * (len(trials) != 1)} found no base{attempts}: "
                       f"{', '.join(map(str, trials))} — {n}")
        else:
            out.append(f"{n}: {store.last_error_line(records.get(cells[0], {}))} (first: {cells[0]})")
    return out
