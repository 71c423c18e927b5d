"""Leases on object storage: what an ``fcntl`` lock does on a local disk, for a sweep on S3.

Object storage has no lock that its holder's death releases, so a holder proves it is alive by
renewing a *lease*. A lease is a series of small JSON objects under one prefix,
``<prefix>/<generation>.json`` (generation = 1, 2, 3 …, zero-padded); the newest one is the lease:

- **acquire**: read the newest generation g (one listing + one GET). If it is held — not released,
  renewed less than ``ttl_s`` ago by the *server's* clock (its Last-Modified against the Date of the
  same listing, so node clocks never matter), and not held by a dead process of this very machine —
  the lease is busy. Otherwise create generation g + 1 with a conditional PUT (``If-None-Match: *``).
  Exactly one of several processes racing for it gets it; the others get 412 and look again.
  Generation numbers are never reused (a release leaves its object, marked released), so a holder
  that was declared dead and comes back can only ever write its own, superseded object.
- **renew**: a daemon thread rewrites the holder's own object every ``renew_s`` seconds (one PUT),
  after checking that no newer generation exists; if one does, the lease was lost (the holder was
  silent for longer than ``ttl_s``) and ``on_lost`` is called.
- **release**: the thread stops and the object is rewritten with ``released: true``; older
  generations are deleted.

A holder killed by SIGKILL leaves a live-looking lease: another machine waits until it lapses
(``ttl_s`` after its last renewal); the same machine sees at once that the process is gone (pid and
its start time from /proc, the boot id) and takes the lease over.

Only conditional *creation* is needed (no If-Match compare-and-swap, which fewer S3-compatible
stores implement): AWS S3, MinIO and R2 document If-None-Match on PutObject, and moto honours it.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import threading
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable

from asp_dist.errors import StorageError
from asp_dist.results.s3 import S3Path, server_listing

LEASE_TTL_S = 30.0
RENEW_EVERY_S = 5.0
_DIGITS = 12


def _boot_id() -> str:
    try:
        with open("/proc/sys/kernel/random/boot_id") as fh:
            return fh.read().strip()
    except OSError:
        return ""


def _start_time(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (field 22 of /proc/PID/stat), None if gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            text = fh.read()
    except OSError:
        return None
    return text[text.rindex(b")") + 2:].split()[19].decode()


def process_alive(pid: int, started: str | None) -> bool:
    """Whether the process that wrote a record on this machine still runs (a reused pid is not it)."""
    if not os.path.isdir("/proc/self"):  # no /proc: assume alive, the lease will lapse
        return True
    now = _start_time(pid)
    return now is not None and (started is None or now == started)


@dataclass
class LeaseState:
    generation: int
    record: dict[str, Any]
    age_s: float  # since its last renewal, on the server's clock

    def live(self, ttl_s: float) -> bool:
        rec = self.record
        if rec.get("released") or self.age_s > float(rec.get("ttl_s", ttl_s)):
            return False
        if rec.get("host") == socket.gethostname() and rec.get("boot_id") == _boot_id() \
                and isinstance(rec.get("pid"), int) and not process_alive(rec["pid"], rec.get("pid_start")):
            return False  # its holder died on this machine (SIGKILL): no need to wait for the lease to lapse
        return True

    def describe(self) -> str:
        holder = self.record.get("holder") or "another process"
        return (f"{holder}; lease renewed {self.age_s:.0f} s ago, lapses "
                f"{float(self.record.get('ttl_s', LEASE_TTL_S)):.0f} s after its last renewal")


class Lease:
    """One lease under ``prefix`` (an S3Path). ``try_acquire`` never waits; ``release`` is idempotent."""

    def __init__(self, prefix: S3Path, ttl_s: float = LEASE_TTL_S, renew_s: float = RENEW_EVERY_S,
                 on_lost: Callable[[str], None] | None = None):
        if renew_s >= ttl_s:
            raise ValueError("a lease must be renewed more often than it lapses")
        self.prefix, self.ttl_s, self.renew_s, self.on_lost = prefix, ttl_s, renew_s, on_lost
        self.generation: int | None = None
        self.lost = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._since = datetime.now(timezone.utc).isoformat(timespec="seconds")

    def _object(self, generation: int) -> S3Path:
        return self.prefix / f"{generation:0{_DIGITS}d}.json"

    def _generations(self) -> tuple[dict[int, dict[str, Any]], datetime]:
        objects, server_now = server_listing(self.prefix)
        found = {}
        for obj in objects:
            name = obj["Key"].rsplit("/", 1)[-1]
            if name.endswith(".json") and name[:-5].isdigit():
                found[int(name[:-5])] = obj
        return found, server_now

    def current(self) -> LeaseState | None:
        """The newest generation, or None when there has never been one."""
        for _ in range(5):
            found, server_now = self._generations()
            if not found:
                return None
            generation = max(found)
            try:
                record = json.loads(self._object(generation).read_text())
            except FileNotFoundError:
                continue  # deleted between the listing and the read (a release cleaning up): look again
            except ValueError:
                record = {"holder": "an unreadable lease record"}
            age = (server_now - found[generation]["LastModified"]).total_seconds()
            return LeaseState(generation, record if isinstance(record, dict) else {}, max(0.0, age))
        return None

    def holder(self) -> str | None:
        """Who holds the lease now (as LeaseState.describe), or None if nobody does. Reads only."""
        state = self.current()
        return state.describe() if state is not None and state.live(self.ttl_s) else None

    def _record(self, released: bool = False) -> bytes:
        pid = os.getpid()
        return json.dumps({"holder": f"pid {pid} on {socket.gethostname()} since {self._since}",
                           "host": socket.gethostname(), "pid": pid, "pid_start": _start_time(pid),
                           "boot_id": _boot_id(), "ttl_s": self.ttl_s, "released": released,
                           "generation": self.generation,
                           "written_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}).encode()

    def try_acquire(self) -> LeaseState | None:
        """Take the lease if nobody holds it. Returns None on success, else the holder's state."""
        if self.generation is not None:
            raise RuntimeError("lease already held")
        state = self.current()
        if state is not None and state.live(self.ttl_s):
            return state
        generation = (state.generation if state is not None else 0) + 1
        self.generation = generation
        if not self._object(generation).create(self._record()):
            self.generation = None
            again = self.current()  # someone else took this generation a moment ago
            return again if again is not None else state
        self._since = datetime.now(timezone.utc).isoformat(timespec="seconds")
        self._cleanup(below=generation)
        self._thread = threading.Thread(target=self._renew, name=f"asp-lease-{self.prefix.name}", daemon=True)
        self._thread.start()
        return None

    def _cleanup(self, below: int) -> None:
        try:
            found, _ = self._generations()
            for generation in found:
                if generation < below:
                    self._object(generation).unlink(missing_ok=True)
        except StorageError:
            pass  # leftovers of older generations are harmless

    def _renew(self) -> None:
        while not self._stop.wait(self.renew_s):
            try:
                found, _ = self._generations()
                if found and max(found) > self.generation:
                    self.lost = True
                    if self.on_lost is not None:
                        self.on_lost(f"lease {self.prefix} was taken over (generation {max(found)}) after this "
                                     f"process could not renew it for {self.ttl_s:.0f} s")
                    return
                self._object(self.generation).write_bytes(self._record())
            except StorageError as err:  # a transient outage: try again at the next tick
                print(f"asp-dist: warning: could not renew {self.prefix}: {err}", file=sys.stderr)

    def release(self) -> None:
        if self.generation is None:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(self.renew_s + 60)
        if not self.lost:
            try:
                self._object(self.generation).write_bytes(self._record(released=True))
            except StorageError as err:
                print(f"asp-dist: warning: could not release {self.prefix} ({err}); it lapses in "
                      f"{self.ttl_s:.0f} s", file=sys.stderr)
        self.generation = None
        self._thread = None
        self._stop = threading.Event()
