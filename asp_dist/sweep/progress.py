"""The counter line of a running sweep: cells done / running / failed / pending, elapsed time, ETA.

A cell's own progress is something else: ProgressFn callbacks (asp_dist.domains.contract), which
`asp-dist cell` prints with cli.CellProgressPrinter. Knows nothing of Ray: the sweep feeds it
counts. On a terminal one line is redrawn in place (at most every ``min_interval_s``); into a
pipe or log file a full line is printed whenever the counts change, and otherwise at most every
``log_interval_s``, so logs stay short.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import TextIO


def format_duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


@dataclass
class Counts:
    total: int
    done: int = 0
    running: int = 0
    failed: int = 0

    @property
    def pending(self) -> int:
        return max(0, self.total - self.done - self.running - self.failed)


class SweepCounter:
    """Counts of one sweep run, printed as one line: redrawn on a terminal, appended in a log."""

    def __init__(self, name: str, total: int, already_done: int = 0, stream: TextIO | None = None,
                 min_interval_s: float = 0.5, log_interval_s: float = 30.0):
        self.name = name
        self.counts = Counts(total=total, done=already_done)
        self.already_done = already_done
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.monotonic()
        self.min_interval_s, self.log_interval_s = min_interval_s, log_interval_s
        self._last_draw = 0.0
        self._last_line = ""

    def eta_s(self) -> float | None:
        """Remaining time from this run's throughput (cells finished before it started do not count)."""
        finished_now = self.counts.done - self.already_done
        remaining = self.counts.total - self.counts.done - self.counts.failed
        if remaining == 0:
            return 0.0
        if finished_now <= 0:
            return None
        return (time.monotonic() - self.start) / finished_now * remaining

    def line(self) -> str:
        c = self.counts
        return (f"[{self.name}] done {c.done}/{c.total}  running {c.running}  failed {c.failed}  "
                f"pending {c.pending}  elapsed {format_duration(time.monotonic() - self.start)}  "
                f"ETA {format_duration(self.eta_s())}")

    def update(self, *, done: int | None = None, running: int | None = None, failed: int | None = None,
               force: bool = False) -> None:
        if done is not None:
            self.counts.done = done
        if running is not None:
            self.counts.running = running
        if failed is not None:
            self.counts.failed = failed
        self.draw(force=force)

    def draw(self, force: bool = False) -> None:
        now = time.monotonic()
        text = self.line()
        counts_part = text.split("  elapsed")[0]
        if self.tty:
            if force or now - self._last_draw >= self.min_interval_s:
                self.stream.write("\r\x1b[K" + text)
                self.stream.flush()
                self._last_draw = now
        elif force or counts_part != self._last_line or now - self._last_draw >= self.log_interval_s:
            self.stream.write(text + "\n")
            self.stream.flush()
            self._last_draw = now
        self._last_line = counts_part

    def finish(self) -> None:
        self.draw(force=True)
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
