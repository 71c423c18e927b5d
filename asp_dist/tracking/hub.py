"""The hub that owns a sweep's trackers, and the feed a worker sends its cells' points through.

In a sweep the hub is a Ray actor on the driver's node (asp_dist.sweep.tune starts it, named after the
sweep: ``hub_name``), so only that node needs the trackers' libraries, files and network; workers anywhere
in the cluster find it by name and send it points without waiting (``Feed``); only a cell's end is waited
for. A plain ``Hub`` works without Ray (the tests drive it directly).

What the hub guarantees:
- one tracker run per cell, opened at the cell's first point (or its end, for a cell that failed first);
- per tracker and cell, only points newer than the last step the run holds: a retried or resumed cell
  resends its restored curve and the hub passes on what the tracker has not seen (after a driver restart the
  tracker reads its last step back from its own storage);
- a tracker that raises is switched off for the rest of the run with one warning; the cells go on;
- a cell's row is written only once the hub has taken its end (``Feed.finish`` waits for it, at most
  FINISH_WAIT_S): a cell with a row has its whole curve and its end in every tracker, also when the driver is
  killed a moment later (a resume never runs that cell again, so nothing else would send them). The wait
  includes what the hub has queued before it (other workers' points, slow trackers' calls). A hub that does
  not answer in time, or is gone, is not waited for again by that worker process (one warning).
"""

from __future__ import annotations

import sys
import time
from typing import Any, Callable, Sequence

from asp_dist.tracking import tracker_class
from asp_dist.tracking.base import STOPPED, Tracker, TrackingSettings
from asp_dist.tracking.cells import CellInfo

SEND_EVERY_S = 1.0  # a worker sends its buffered points at most this often (and at every cell's end)
# How long a worker waits for the hub to take a cell's end before writing its row anyway, once: a hub held up
# past it (a tracker server that went away: MLflow gives up after about 3 x --connect-timeout) is not waited
# for again by that worker.
FINISH_WAIT_S = 90.0


def hub_name(sweep: str) -> str:
    return f"asp-dist-trackers:{sweep}"


def final_metrics(row: dict[str, Any], fields: frozenset[str] = frozenset()) -> dict[str, float]:
    """A row's final metrics for the trackers: its eval_* numbers that are not spec `fields` (eval_episodes)."""
    return {k: float(v) for k, v in row.items() if k.startswith("eval_") and k not in fields
            and isinstance(v, (int, float)) and not isinstance(v, bool)}


class Hub:
    def __init__(self, settings: TrackingSettings, sweep: str, cells: dict[str, CellInfo]):
        self.cells = cells
        self.warnings: list[str] = []
        self.trackers: list[Tracker] = []
        self.last: dict[tuple[str, str], int] = {}  # (tracker kind, cell id) -> last step its run holds
        self.open: set[str] = set()
        for kind in settings.loggers:
            tracker = tracker_class(kind)(settings, sweep)
            try:
                tracker.start()
            except Exception as e:  # noqa: BLE001 - any failure of a tracker is a warning, never a stop
                self._warn(tracker, "could not start", e)
                continue
            self.trackers.append(tracker)

    def ready(self) -> list[str]:
        """The warnings so far, once the trackers have started (the driver's first poll)."""
        return self.take_warnings()

    def _warn(self, tracker: Tracker, what: str, e: BaseException) -> None:
        self.warnings.append(f"asp-dist: warning: logger {tracker.kind} {what} ({type(e).__name__}: "
                             f"{str(e).strip().splitlines()[0] if str(e).strip() else ''}); it is off for the "
                             f"rest of this run, the cells and their rows are unaffected")

    def _each(self, what: str, fn) -> None:
        for tracker in list(self.trackers):
            try:
                fn(tracker)
            except Exception as e:  # noqa: BLE001 - see _warn
                self.trackers.remove(tracker)
                self._warn(tracker, what, e)

    def _opened(self, tracker: Tracker, cell: CellInfo) -> int:
        key = (tracker.kind, cell.cell_id)
        if key not in self.last:
            held = tracker.open_cell(cell)
            self.last[key] = -1 if held is None else int(held)
            self.open.add(cell.cell_id)
        return self.last[key]

    def points(self, batch: Sequence[tuple[str, list[dict[str, Any]]]]) -> None:
        """Curve points of cells, [(cell id, points in step order)]."""
        def send(tracker: Tracker) -> None:
            for cell_id, points in batch:
                cell = self.cells[cell_id]
                last = self._opened(tracker, cell)
                new = [p for p in points if int(p["step"]) > last]
                if new:
                    tracker.log(cell, new)
                    self.last[(tracker.kind, cell_id)] = int(new[-1]["step"])

        self._each("failed while logging", send)

    def finish(self, cell_id: str, final: dict[str, float], step: int, error: str | None = None) -> None:
        """A cell ended: its final metrics at its last step, or the error it failed with."""
        cell = self.cells[cell_id]

        def end(tracker: Tracker) -> None:
            self._opened(tracker, cell)
            tracker.finish(cell, final, step, error)
            self.last.pop((tracker.kind, cell_id), None)

        self._each("failed ending a cell", end)
        self.open.discard(cell_id)

    def take_warnings(self) -> list[str]:
        out, self.warnings = self.warnings, []
        return out

    def close(self, interrupted: bool) -> list[str]:
        """End the run: cells still open are ended as stopped (a resume continues their runs), then every
        tracker closes. Returns the warnings not yet taken."""
        for cell_id in sorted(self.open):
            step = max((s for (kind, c), s in self.last.items() if c == cell_id), default=0)
            self.finish(cell_id, {}, max(step, 0), STOPPED)
        self._each("failed closing", lambda t: t.close(interrupted))
        return self.take_warnings()


class Feed:
    """A worker's side: as the pipeline's on_points (asp_dist.training.pipeline.PointsFn) it buffers each
    cell's new points (of the cells in `only`, when given) and sends them to the hub at most every
    SEND_EVERY_S, without waiting (actor calls are asynchronous, and kept in order per worker). ``finish``
    sends what is left and the cell's end, and waits until the hub has taken them, so that the caller writes
    the cell's row only after its trackers have its end. `wait(ref, seconds) -> bool` waits for an actor call's
    answer (asp_dist.sweep.trial's, in a sweep); None: nothing is waited for."""

    def __init__(self, hub: Any, every_s: float = SEND_EVERY_S, only: set[str] | None = None,
                 wait: Callable[[Any, float], bool] | None = None, finish_wait_s: float = FINISH_WAIT_S):
        self.hub, self.every_s, self.only = hub, every_s, only
        self.wait, self.finish_wait_s = wait, finish_wait_s
        self.buffer: dict[str, list[dict[str, Any]]] = {}
        self.sent_at = time.monotonic()

    def __call__(self, batch) -> None:
        for spec, points in batch:
            if self.only is None or spec.cell_id in self.only:
                self.buffer.setdefault(spec.cell_id, []).extend(points)
        if time.monotonic() - self.sent_at >= self.every_s:
            self.flush()

    def flush(self) -> None:
        if self.buffer:
            self.hub.points.remote(list(self.buffer.items()))
            self.buffer = {}
        self.sent_at = time.monotonic()

    def finish(self, cell_id: str, final: dict[str, float], step: int, error: str | None = None) -> bool:
        """Send the cell's last points and its end, and wait for the hub to take them. False when it did not
        answer within finish_wait_s (or is gone): one warning, and this feed waits for it no more."""
        self.flush()
        answer = self.hub.finish.remote(cell_id, final, step, error)
        if self.wait is None or self.wait(answer, self.finish_wait_s):
            return True
        self.wait = None
        print(f"asp-dist: warning: the tracker hub did not take cell {cell_id}'s end within "
              f"{self.finish_wait_s:g} s (or is gone); its row is written without it, and this worker no longer "
              f"waits for the hub", file=sys.stderr, flush=True)
        return False
