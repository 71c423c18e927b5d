"""JSON lines: one file per cell, DIR/json/<run path>.jsonl, one line per curve point as it closes
({"step": …, "loss_paired": …, …}, the curve's own keys), a first line with the cell's tags and config and
a last line {"final": {eval_*: …}, "step": …, "error": …}. What ``tail -f`` or a notebook reads while the sweep
runs; the Parquet curve written at the cell's end holds the same points. A resumed cell appends after the
last whole line (a line cut short by a crash is dropped first).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from asp_dist.tracking.base import Tracker, TrackingSettings
from asp_dist.tracking.cells import CellInfo


class JsonLinesTracker(Tracker):
    kind = "json"
    module = "json"
    install = "(the standard library)"
    subdir = "json"

    def __init__(self, settings: TrackingSettings, sweep: str):
        super().__init__(settings, sweep)
        self.files: dict[str, Any] = {}

    def path(self, cell: CellInfo) -> Path:
        return self.root / f"{cell.run_path}.jsonl"

    def open_cell(self, cell: CellInfo) -> int | None:
        path = self.path(cell)
        path.parent.mkdir(parents=True, exist_ok=True)
        last = None
        if path.exists():
            text = path.read_text()
            whole = text[:text.rfind("\n") + 1]
            if whole != text:
                path.write_text(whole)  # a line cut short by a crash
            steps = [json.loads(line).get("step") for line in whole.splitlines() if line.strip()]
            last = max((int(s) for s in steps if s is not None), default=None)
        self.files[cell.cell_id] = f = path.open("a")
        if last is None:
            f.write(json.dumps({"cell": cell.tags, "config": cell.config}, default=str) + "\n")
            f.flush()
        return last

    def log(self, cell: CellInfo, points: list[dict[str, Any]]) -> None:
        f = self.files[cell.cell_id]
        f.write("".join(json.dumps(dict(p, step=int(p["step"]))) + "\n" for p in points))
        f.flush()

    def finish(self, cell: CellInfo, final: dict[str, float], step: int, error: str | None) -> None:
        f = self.files.pop(cell.cell_id)
        f.write(json.dumps({"final": final, "final_step": step, "error": error}) + "\n")
        f.close()

    def close(self, interrupted: bool) -> None:
        for f in self.files.values():
            f.close()
        self.files.clear()
