"""The reaper of an embedded Ray: kills what is left of it when its driver ends, however it ends.

Ray's raylet and GCS die with the driver (PR_SET_PDEATHSIG), but after a SIGKILL of the driver the raylet's
agents spend a minute trying to tell the dead GCS about it, and workers may take a few seconds. The reaper is
a tiny process (standard library only: no Ray, no torch, not even asp_dist) that the driver starts before
Ray (`sweep.tune._start_reaper`, which runs this file by path with ``python -I -S``) and that waits for the
driver to close a pipe — at the end of the Ray session, or when the driver dies.

While it waits it keeps a family tree: the node processes the driver starts (children whose command line
names the Ray temp dir) and every descendant of those, by (pid, start time) so that a reused pid is never
mistaken for ours. It scans /proc twice a second while Ray starts, then every 2 s (a few ms each). At the
end it kills the family, and also every process of the raylet it saw (RAY_RAYLET_PID in its environment),
which catches a worker born after the last scan, and repeats until two scans in a row find none. It writes
what it did to ``reaper-<driver pid>.log`` in the temp dir, for whoever wonders what survived.

    python -I -S reaper.py DRIVER_PID RAY_TEMP_DIR    (stdin: the pipe whose end of file means "done")
"""

from __future__ import annotations

import os
import select
import signal
import sys
import time
from typing import Callable, TextIO

Stat = tuple[bytes, int, int]  # (command name, parent pid, start time in clock ticks)


def stat(pid: int) -> Stat | None:
    """/proc/<pid>/stat's command name, parent pid and start time, or None for a process that is gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read()
    except OSError:
        return None
    fields = data[data.rindex(b")") + 2:].split()  # the name may hold spaces and parentheses
    return data[data.index(b"(") + 1:data.rindex(b")")], int(fields[1]), int(fields[19])


def read(pid: int, name: str) -> list[bytes]:
    """A NUL-separated /proc/<pid> file (cmdline, environ) as its items; [] if unreadable."""
    try:
        with open(f"/proc/{pid}/{name}", "rb") as f:
            return f.read().split(b"\0")
    except OSError:
        return []


def snapshot(skip: tuple[int, ...]) -> dict[int, Stat]:
    """Every process but those in `skip`: pid -> stat."""
    found = {}
    for p in os.listdir("/proc"):
        if p.isdigit() and int(p) not in skip:
            st = stat(int(p))
            if st:
                found[int(p)] = st
    return found


class Family:
    """The driver's Ray: its node processes and their descendants, each by (pid, start time)."""

    def __init__(self, driver: int, temp_dir: bytes, cmdline: Callable[[int], list[bytes]], log: TextIO | None,
                 started: float) -> None:
        self.driver, self.temp_dir, self.cmdline, self.log, self.started = driver, temp_dir, cmdline, log, started
        self.tracked: dict[int, int] = {}  # pid -> start time
        self.raylet: tuple[int, int] | None = None  # (pid, start time)

    def scan(self, procs: dict[int, Stat]) -> None:
        for pid, (name, ppid, start) in procs.items():
            if pid not in self.tracked and ppid == self.driver and any(self.temp_dir in a for a in self.cmdline(pid)):
                self.tracked[pid] = start
                self._note("node process %d %s" % (pid, name.decode(errors="replace")))
                if name == b"raylet" and self.raylet is None:
                    self.raylet = (pid, start)
        grew = True
        while grew:  # descendants (children appear after their parents in no fixed order)
            grew = False
            for pid, (_, ppid, start) in procs.items():
                if pid not in self.tracked and self.tracked.get(ppid, start + 1) <= start:
                    self.tracked[pid] = start
                    grew = True
        for pid in [p for p, s in self.tracked.items() if procs.get(p, (b"", 0, None))[2] != s]:
            del self.tracked[pid]  # gone (or its pid reused): forget it

    def ours(self, pid: int, start: int, environ: Callable[[int], list[bytes]]) -> bool:
        """Tracked, or a process of the raylet we saw born after it (its environment names the raylet)."""
        return self.tracked.get(pid) == start or (
            self.raylet is not None and start >= self.raylet[1]
            and b"RAY_RAYLET_PID=%d" % self.raylet[0] in environ(pid))

    def _note(self, text: str) -> None:
        if self.log is not None:
            self.log.write("%.1f s: %s\n" % (time.monotonic() - self.started, text))


def reap(family: Family, skip: tuple[int, ...]) -> None:
    """Kill the family until two scans in a row find nothing of it (at most ~6 s)."""
    quiet = 0
    for _ in range(20):
        killed = []
        for pid, (name, _, start) in snapshot(skip).items():
            if family.ours(pid, start, lambda p: read(p, "environ")):
                try:
                    os.kill(pid, signal.SIGKILL)
                    killed.append("%d %s" % (pid, name.decode(errors="replace")))
                except OSError:
                    pass
        if killed:
            family._note("killed " + ", ".join(killed))
        quiet = 0 if killed else quiet + 1
        if quiet == 2:
            return
        time.sleep(0.3)


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle; this cleans up after it
    driver, temp_dir = int(argv[0]), argv[1]
    os.makedirs(temp_dir, exist_ok=True)
    started = time.monotonic()
    with open(os.path.join(temp_dir, "reaper-%d.log" % driver), "a", buffering=1) as log:
        family = Family(driver, os.fsencode(temp_dir), lambda p: read(p, "cmdline"), log, started)
        skip = (driver, os.getpid())
        while True:
            fast = family.raylet is None or time.monotonic() - started < 30
            if select.select([0], [], [], 0.5 if fast else 2.0)[0] and not os.read(0, 4096):
                break  # end of file: the driver closed the pipe or died
            family.scan(snapshot(skip))
        family._note("the driver is done; raylet %s, tracking %d" % (family.raylet, len(family.tracked)))
        reap(family, skip)
        family._note("done")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
