"""Pre-flight checks: everything a user can get wrong about a sweep, refused in one line before anything is
written and before Ray is imported — the results directory (local or S3), the run's numbers, a cluster
address that nothing answers on, a grid that differs from the stored one, a sweep that is running.

`sweep` and `resume` run the read-only checks early (check_can_start, check_can_resume: the CLI's first
answers) and the run repeats the writing ones under its lock (asp_dist.sweep.tune). No Ray import.
"""

from __future__ import annotations

import math
import os
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from asp_dist.errors import SpecError, SweepError
from asp_dist.results import store
from asp_dist.results.location import AnyPath
from asp_dist.results.s3 import S3Path, check_bucket
from asp_dist.spec import CellSpec
from asp_dist.sweep.ledger import (
    DEFAULT_CONNECT_TIMEOUT_S,
    _sweep_lease,
    check_manifest_shape,
    extended_manifest,
    lock_holder,
    new_manifest,
    read_sweep,
    sweep_dir_for,
)
from asp_dist.sweep.packing import Packing, resolve_packing
from asp_dist.sweep.spaces import grid_hash

# A check's `manifest` argument: the sweep's manifest as the caller read it (None: it has none), so that one run
# reads it once before its lock and once under it; UNREAD (the default) reads it here.
UNREAD: Any = type("Unread", (), {"__repr__": lambda self: "UNREAD"})()


def _manifest(sweep_dir: AnyPath, manifest: Any) -> dict[str, Any] | None:
    return store.read_manifest(sweep_dir) if manifest is UNREAD else manifest


# ---- where the sweep lives -----------------------------------------------------------------------
def _remote_is_foreign(sweep_dir: S3Path, manifest: Any = UNREAD) -> bool:
    """An S3 prefix with objects but no manifest: not a sweep (hidden names such as a lease or a write
    probe left by an interrupted start do not count)."""
    if _manifest(sweep_dir, manifest) is not None:
        return False
    return any(store.visible(p, sweep_dir) for p in sweep_dir.rglob("*"))


def _check_remote_sweep_dir(sweep_dir: S3Path, write_probe: bool, manifest: Any = UNREAD) -> None:
    check_bucket(sweep_dir)
    if _remote_is_foreign(sweep_dir, manifest):
        raise SweepError(f"{sweep_dir} holds objects and is not a sweep (no manifest.json); choose another --name")
    if write_probe:  # credentials that may read but not write are refused before anything else is written
        probe = sweep_dir / f".write-test-{os.getpid()}-{int(time.time() * 1000)}"
        try:
            probe.write_bytes(b"")
            probe.unlink(missing_ok=True)
        except SpecError as e:
            raise SweepError(f"results prefix {sweep_dir.parent} is not writable ({e}); choose another "
                             f"with --results") from None


def check_sweep_dir(sweep_dir: AnyPath, manifest: Any = UNREAD) -> None:
    """Refuse to start in a directory that holds something other than a sweep, or cannot be written."""
    if isinstance(sweep_dir, S3Path):
        _check_remote_sweep_dir(sweep_dir, write_probe=True, manifest=manifest)
        return
    if sweep_dir.exists() and _manifest(sweep_dir, manifest) is None and any(sweep_dir.iterdir()):
        raise SweepError(f"{sweep_dir} exists and is not a sweep (no manifest.json); choose another --name")
    try:
        sweep_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=sweep_dir, prefix=".write-test-"):
            pass
    except OSError as e:
        raise SweepError(f"results dir {sweep_dir.parent} is not writable ({e.strerror or e}); "
                         f"choose another with --results") from None


def _nearest_existing(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_sweep_dir_readonly(sweep_dir: AnyPath, manifest: Any = UNREAD) -> None:
    """check_sweep_dir without touching the disk: what a run would refuse, refused before anything is written."""
    if isinstance(sweep_dir, S3Path):
        _check_remote_sweep_dir(sweep_dir, write_probe=False, manifest=manifest)
        return
    if sweep_dir.exists() and not sweep_dir.is_dir():
        raise SweepError(f"{sweep_dir} exists and is not a directory; choose another --name or --results")
    if sweep_dir.is_dir() and _manifest(sweep_dir, manifest) is None and any(sweep_dir.iterdir()):
        raise SweepError(f"{sweep_dir} exists and is not a sweep (no manifest.json); choose another --name")
    existing = _nearest_existing(sweep_dir)
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        why = "not a directory" if not existing.is_dir() else "read-only"
        raise SweepError(f"results dir {sweep_dir.parent} is not writable ({existing} is {why}); "
                         f"choose another with --results")


def check_run_options(workers: int, max_failures: int, checkpoint_every_s: float,
                      connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S) -> None:
    """The numbers of a run, refused before Ray is imported."""
    for flag, value in (("--workers", workers), ("--max-failures", max_failures)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise SweepError(f"{flag} must be an integer, got {value!r}")
    if workers < 1:
        raise SweepError(f"--workers must be >= 1, got {workers}")
    if max_failures < 0:
        raise SweepError(f"--max-failures must be >= 0, got {max_failures}")
    for flag, value in (("--checkpoint-every", checkpoint_every_s), ("--connect-timeout", connect_timeout_s)):
        if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                and value > 0):
            raise SweepError(f"{flag} must be > 0 seconds and finite, got {value}")


# ---- the cluster address -------------------------------------------------------------------------
def parse_address(address: str) -> tuple[str, int] | None:
    """(host, port) of --address (HOST:PORT, [IPv6]:PORT or ray://HOST:PORT); None for "auto"."""
    text = address.strip()
    if text == "auto":
        return None
    if text.startswith("ray://"):
        text = text[len("ray://"):]
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise SweepError(f"--address {address!r}: write HOST:PORT of the cluster's head (e.g. 127.0.0.1:6379)")
    return host, int(port)


def _resolve(host: str, port: int, timeout_s: float) -> list[tuple]:
    """getaddrinfo with a deadline: the resolver's own retries can take much longer than --connect-timeout."""
    answer: list = []

    def lookup() -> None:
        try:
            answer.append(socket.getaddrinfo(host, port, type=socket.SOCK_STREAM))
        except OSError as e:
            answer.append(e)

    thread = threading.Thread(target=lookup, daemon=True)
    thread.start()
    thread.join(timeout_s)
    if not answer:
        raise TimeoutError(f"no answer from the resolver for {host!r}")
    if isinstance(answer[0], OSError):
        raise answer[0]
    return answer[0]


def check_address(address: str, timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S) -> None:
    """Refuse, within ``timeout_s``, a cluster address nothing answers on: resolve the head and open a TCP
    connection to it, retrying while a head may still be starting. Needs no Ray, so it runs before Ray is
    imported and before anything is written. ("auto" is Ray's to find; it is bounded by tune.ray_session.)"""
    parsed = parse_address(address)
    if parsed is None:
        return
    host, port = parsed
    deadline = time.monotonic() + timeout_s
    why = "no answer"
    while (remaining := deadline - time.monotonic()) > 0:
        try:
            for family, kind, proto, _, sockaddr in _resolve(host, port, remaining):
                with socket.socket(family, kind, proto) as sock:
                    sock.settimeout(max(0.1, min(5.0, deadline - time.monotonic())))
                    try:
                        sock.connect(sockaddr)
                        return
                    except OSError as e:
                        why = e.strerror or type(e).__name__
        except socket.gaierror as e:
            if e.errno != socket.EAI_AGAIN:  # an unknown host stays unknown: no point in waiting
                raise SweepError(f"cannot reach the Ray cluster at {address}: unknown host {host!r} "
                                 f"({e.strerror}); check --address") from None
            why = e.strerror or "resolver failed"
        except (OSError, TimeoutError) as e:
            why = str(e) or type(e).__name__
        time.sleep(min(0.5, max(0.0, deadline - time.monotonic())))
    raise SweepError(f"cannot reach the Ray cluster at {address} within {timeout_s:g} s ({why}); "
                     f"check --address, or raise --connect-timeout")



# ---- the grid and the lock ----------------------------------------------------------------------
def check_manifest(sweep_dir: AnyPath, name: str, specs: list[CellSpec], space: str,
                   packing: Packing | None = None, extend: bool = False, manifest: Any = UNREAD) -> dict[str, Any]:
    """The sweep's manifest (a new one, with `packing`, if it has none); refuses a grid that differs from
    the stored one (`manifest`), unless `extend` and the new grid only adds cells (ledger.extended_manifest:
    then the manifest of the grown grid, to be written before any new cell runs)."""
    existing = _manifest(sweep_dir, manifest)
    if existing is None:
        return new_manifest(name, space, specs, packing)
    digest, stored = grid_hash(specs), existing.get("grid_hash")
    if stored == digest:
        return existing
    if extend:
        return extended_manifest(existing, space, specs)
    grows = set(existing["cells"]) < {s.cell_id for s in specs}
    raise SweepError(f"sweep {name!r} in {sweep_dir.parent} was started with another grid (space "
                     f"{existing.get('space')!r}, {len(existing['cells'])} cells, hash {stored}; "
                     f"now {space!r}, {len(specs)} cells, hash {digest}); use another --name"
                     + (", or --extend to add the new cells to this sweep" if grows else ""))


def check_not_running(sweep_dir: AnyPath) -> None:
    if isinstance(sweep_dir, S3Path):  # a silent lease (driver killed elsewhere) is waited out by the run itself
        lease = _sweep_lease(sweep_dir)
        state = lease.current()
        live = state is not None and state.live(lease.ttl_s) and state.age_s <= 2 * lease.renew_s
        holder = state.describe() if live else None
    else:
        holder = lock_holder(sweep_dir)
    if holder is not None:
        raise SweepError(f"sweep {sweep_dir.name!r} is already running ({holder}); wait for it to finish "
                         f"or use another --name")


def check_can_start(results: str | AnyPath, name: str, specs: list[CellSpec], space: str,
                    pack: str | None = None, pack_size: int | None = None, extend: bool = False) -> dict[str, Any] | None:
    """Everything `sweep` refuses about where it would run, checked without writing: the name, the
    results dir, a directory that is not a sweep, a sweep started with another grid or packing, a
    running sweep. Returns the sweep's manifest as read here (None: a new sweep), for the plan to carry.
    The run checks them again under its lock (tune._run); this is the early, read-only answer."""
    sweep_dir = sweep_dir_for(results, name)
    manifest = store.read_manifest(sweep_dir)  # None also where sweep_dir is a file: refused next
    check_sweep_dir_readonly(sweep_dir, manifest)
    resolve_packing(pack, pack_size, manifest)
    if pack in ("trial", "method"):
        check_something_packs(specs, space, pack)
    if manifest is not None:
        check_manifest_shape(manifest, sweep_dir)
        check_manifest(sweep_dir, name, specs, space, extend=extend, manifest=manifest)
        check_not_running(sweep_dir)
    return manifest


def check_something_packs(specs: list[CellSpec], space: str, pack: str) -> None:
    """--pack asked for a grid none of whose cells a packed trainer takes (the flag would change nothing): refused.
    A grid where some cells pack runs the others one cell per trial, as documented."""
    from asp_dist.core.registry import get_domain
    from asp_dist.training.engines import sweep_packs

    if not specs or any(sweep_packs(s) for s in specs):
        return
    reasons = []
    for domain in sorted({s.domain for s in specs}):
        packers = [t for t in get_domain(domain).trainers if getattr(t, "packs", False)]
        reasons.append(f"{domain} has no packed trainer" if not packers
                       else f"{domain}'s packed trainer is kept out of sweeps" if not any(t.in_sweeps for t in packers)
                       else f"{domain}'s packed trainer does not take these cells' knob values")
    why = "; ".join(reasons)
    raise SweepError(f"--pack {pack}: none of the {len(specs)} cells of {space} can be packed ({why}); "
                     f"leave out --pack to run one cell per trial")


def check_can_resume(results: str | AnyPath, name: str, pack: str | None = None,
                     pack_size: int | None = None) -> dict[str, Any]:
    """Everything `resume` refuses, checked without writing; returns the sweep's manifest (read once)."""
    sweep_dir, manifest = read_sweep(results, name)
    resolve_packing(pack, pack_size, manifest)
    check_sweep_dir_readonly(sweep_dir, manifest)
    check_not_running(sweep_dir)
    return manifest
