"""What a running sweep shows: cells done / running / failed / pending per domain and method,
cells per minute, ETA, the last failure's reason and where the rows go.

A cell's own progress is something else: ProgressFn callbacks (asp_dist.core.contract), which
`asp-dist cell` prints with asp_dist.commands.cell.CellProgressPrinter. Knows nothing of Ray: the sweep feeds it the
ids of the cells that are done, failed and running.

On a terminal the view is one live block redrawn in place (rich), at most 80 columns wide. Into a
pipe or a log file it prints one line when the done or failed count changes, at most every
``log_interval_s`` (the running count alone never prints: it flickers as workers hand over), and a
last line at the end — a long sweep's log stays a few hundred lines, not thousands.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from typing import TextIO

WIDTH = 80


def format_duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class SweepCounter:
    """Counts of one sweep run: a live view on a terminal, change-only lines in a log.

    cells      cell id -> its group, "domain/method" (the rows of the view)
    done       ids of the cells that already had a row when this run started
    where      where the rows go (shown under the counts)
    bases      bases this run trains before its packs (asp_dist.sweep.packing.bases_first); `base_finished`
               counts them, and the view says "bases k/n" until they are all trained
    """

    def __init__(self, name: str, cells: dict[str, str], done: set[str] | frozenset[str] = frozenset(),
                 stream: TextIO | None = None, where: str = "", log_interval_s: float = 5.0, bases: int = 0):
        self.name, self.cells, self.where = name, dict(cells), where
        self.bases, self.bases_done = bases, 0
        self.done: set[str] = set(done) & set(cells)
        self.failed: set[str] = set()
        self.running: set[str] = set()
        self.already_done = len(self.done)
        self.last_failure = ""
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = time.monotonic()
        self.log_interval_s = log_interval_s
        self._logged: tuple[int, int, int] | None = None  # (done, failed, bases done) of the last log line
        self._last_log = float("-inf")
        self._live = None

    # ---- numbers ---------------------------------------------------------------------------------
    @property
    def total(self) -> int:
        return len(self.cells)

    @property
    def pending(self) -> int:
        return max(0, self.total - len(self.done) - len(self.running) - len(self.failed))

    def rate_per_min(self) -> float | None:
        """Cells finished per minute by this run (cells done before it started do not count)."""
        elapsed = time.monotonic() - self.start
        finished = len(self.done) - self.already_done
        return finished / elapsed * 60 if finished > 0 and elapsed > 0 else None

    def eta_s(self) -> float | None:
        remaining = self.total - len(self.done) - len(self.failed)
        if remaining == 0:
            return 0.0
        rate = self.rate_per_min()
        return remaining / rate * 60 if rate else None

    def groups(self) -> list[tuple[str, int, int, int, int]]:
        """(group, done, running, failed, pending) per domain/method, in first-seen order."""
        total = Counter(self.cells.values())
        counts = {kind: Counter(self.cells[c] for c in ids if c in self.cells)
                  for kind, ids in (("done", self.done), ("running", self.running), ("failed", self.failed))}
        out = []
        for group in dict.fromkeys(self.cells.values()):
            d, r, f = (counts[k][group] for k in ("done", "running", "failed"))
            out.append((group, d, r, f, max(0, total[group] - d - r - f)))
        return out

    def bases_part(self) -> str:
        """"bases k/n  " while this run's bases are being trained first, else empty."""
        return f"bases {self.bases_done}/{self.bases}  " if self.bases_done < self.bases else ""

    def base_finished(self) -> None:
        self.bases_done += 1
        self.draw()

    def line(self) -> str:
        rate = self.rate_per_min()
        return (f"[{self.name}] {self.bases_part()}done {len(self.done)}/{self.total}  running {len(self.running)}  "
                f"failed {len(self.failed)}  pending {self.pending}  elapsed "
                f"{format_duration(time.monotonic() - self.start)}  "
                f"{'?' if rate is None else f'{rate:.1f}'} cells/min  ETA {format_duration(self.eta_s())}")

    # ---- feeding ---------------------------------------------------------------------------------
    def update(self, *, done: set[str] | None = None, failed: set[str] | None = None,
               running: set[str] | None = None, last_failure: str | None = None, force: bool = False) -> None:
        if done is not None:
            self.done = set(done) & set(self.cells)
        if failed is not None:
            self.failed = set(failed) & set(self.cells)
        if running is not None:
            self.running = set(running) - self.done - self.failed
        if last_failure:
            self.last_failure = last_failure
        self.draw(force=force)

    def draw(self, force: bool = False) -> None:
        if self.tty:
            self._draw_live()
            return
        now = time.monotonic()
        counts = (len(self.done), len(self.failed), self.bases_done)
        if force or (counts != self._logged and now - self._last_log >= self.log_interval_s):
            self.stream.write(self.line() + "\n")
            self.stream.flush()
            self._logged, self._last_log = counts, now

    def finish(self) -> None:
        if self.tty:
            if self._live is not None:
                self._live.update(self.render(), refresh=True)
                self._live.stop()
                self._live = None
        else:
            self.draw(force=True)

    # ---- the live view -----------------------------------------------------------------------------
    def render(self):
        """The view as a rich renderable, at most WIDTH columns."""
        from rich.console import Group
        from rich.table import Table
        from rich.text import Text

        rate = self.rate_per_min()
        bases = f"{self.bases_part().rstrip()}, " if self.bases_part() else ""
        head = Text(f"{self.name}: {bases}{len(self.done)}/{self.total} done, {len(self.running)} running, "
                    f"{len(self.failed)} failed, {self.pending} pending", style="bold")
        pace = Text(f"{'?' if rate is None else f'{rate:.1f}'} cells/min · elapsed "
                    f"{format_duration(time.monotonic() - self.start)} · ETA {format_duration(self.eta_s())}")
        table = Table(box=None, pad_edge=False, header_style="bold", width=min(WIDTH, 60))
        table.add_column("domain/method", no_wrap=True)
        for column in ("done", "running", "failed", "pending"):
            table.add_column(column, justify="right")
        for group, d, r, f, p in self.groups():
            table.add_row(group, str(d), str(r), Text(str(f), style="red" if f else ""), str(p))
        parts = [head, pace, table]
        if self.last_failure:
            parts.append(Text(f"last failure: {self.last_failure}", style="red", overflow="ellipsis", no_wrap=True))
        if self.where:
            parts.append(Text(f"rows → {self.where}", overflow="ellipsis", no_wrap=True))
        return Group(*parts)

    def _draw_live(self) -> None:
        if self._live is None:
            from rich.console import Console
            from rich.live import Live

            console = Console(file=self.stream, width=min(WIDTH, Console(file=self.stream).width))
            self._live = Live(self.render(), console=console, refresh_per_second=2, transient=False,
                              get_renderable=self.render)
            self._live.start()
        else:
            self._live.refresh()
