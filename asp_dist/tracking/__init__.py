"""Live experiment tracking: every cell's curve points reach TensorBoard, MLflow, W&B or JSON lines while it
trains, one tracker run per cell (also for cells trained inside a pack). Off by default; ``--logger KIND``
(repeatable) or a space file's [logging] table switches a tracker on. The Parquet rows stay the truth: a
tracker only reads what the pipeline records, and rows are the same with or without one.

    cells.py        how a cell is named, grouped and tagged (CellInfo)
    base.py         TrackingSettings, the Tracker class, the names trackers show
    tensorboard.py, mlflow.py, wandb.py, jsonl.py: the four trackers
    hub.py          the driver-side hub (a Ray actor in a sweep) that owns the trackers; the worker-side feed

Flow: the pipeline (asp_dist.training.pipeline.run_unit's ``on_points``) hands each member's new curve
points to the worker's Feed, which sends them, about once a second, to the sweep's hub; the hub keeps the
last step each tracker holds per cell (read back from the tracker on a resume) and passes on only newer
points; a tracker that fails is switched off with one warning, never failing a cell or losing a row.
"""

from __future__ import annotations

from asp_dist.tracking.base import Tracker, TrackerError, TrackingSettings

# kind -> "module:Class" (imported when used: a tracker's library is imported only if asked for)
TRACKERS = {
    "tensorboard": "asp_dist.tracking.tensorboard:TensorBoardTracker",
    "mlflow": "asp_dist.tracking.mlflow:MLflowTracker",
    "wandb": "asp_dist.tracking.wandb:WandbTracker",
    "json": "asp_dist.tracking.jsonl:JsonLinesTracker",
}


def tracker_class(kind: str) -> type[Tracker]:
    import importlib

    if kind not in TRACKERS:
        raise TrackerError(f"unknown logger {kind!r}; choose from {', '.join(TRACKERS)}")
    module, name = TRACKERS[kind].split(":")
    return getattr(importlib.import_module(module), name)


def check(settings: TrackingSettings) -> None:
    """Every chosen tracker can start (settings resolved): else one TrackerError line, before anything runs."""
    seen = set()
    for kind in settings.loggers:
        if kind in seen:
            raise TrackerError(f"--logger {kind} is given twice")
        seen.add(kind)
        tracker_class(kind).check(settings)


__all__ = ["TRACKERS", "Tracker", "TrackerError", "TrackingSettings", "check", "tracker_class"]
