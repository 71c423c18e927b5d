"""TensorBoard: one run directory per cell under DIR/tensorboard/, its path the cell's group
(domain/condition/treatment/paired=N/trial=T-<id>), so TensorBoard's run filter finds a condition, a method
or a paired count by prefix. Scalars in sections (loss/, probe/, discriminator/, schedule/, eval/); the
resolved spec as HParams (with the trial, sweep and code revision), its metrics the cell's eval/ scalars.

Written with torch.utils.tensorboard (TensorBoard's own event format), flushed every few seconds so that a
running ``tensorboard --logdir DIR/tensorboard`` shows the curves while the cells train. A resumed cell
continues its directory: the last step it holds is read back with TensorBoard's EventAccumulator.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from asp_dist.tracking.base import Tracker, TrackingSettings, check_writable, hparam, metric_name, scalars
from asp_dist.tracking.cells import CellInfo

FLUSH_SECS = 5  # how stale a live TensorBoard may be


class TensorBoardTracker(Tracker):
    kind = "tensorboard"
    module = "torch.utils.tensorboard"
    install = "tensorboard"

    def __init__(self, settings: TrackingSettings, sweep: str):
        super().__init__(settings, sweep)
        self.root = Path(settings.dir) / "tensorboard"
        self.writers: dict[str, Any] = {}

    @classmethod
    def check(cls, settings: TrackingSettings) -> None:
        super().check(settings)
        check_writable(cls.kind, Path(settings.dir) / "tensorboard")

    def logdir(self, cell: CellInfo) -> Path:
        return self.root / cell.run_path

    def open_cell(self, cell: CellInfo) -> int | None:
        from torch.utils.tensorboard import SummaryWriter

        where = self.logdir(cell)
        last = last_step(where) if where.is_dir() else None
        writer = SummaryWriter(str(where), flush_secs=FLUSH_SECS)
        if last is None:  # a new run: its HParams once (a resumed run has them in its first event file)
            from torch.utils.tensorboard.summary import hparams

            config = {k: hparam(v) for k, v in cell.config.items() if v is not None}
            config.update(sweep=cell.sweep, code_revision=cell.revision, cell_id=cell.cell_id,
                          condition=cell.condition, treatment=cell.treatment)
            exp, ssi, _ = hparams(config, {metric_name(f"eval_{m}"): 0.0 for m in cell.metrics})
            writer.file_writer.add_summary(exp)
            writer.file_writer.add_summary(ssi)
        self.writers[cell.cell_id] = writer
        return last

    def log(self, cell: CellInfo, points: list[dict[str, Any]]) -> None:
        writer = self.writers[cell.cell_id]
        for point in points:
            for tag, value in scalars(point).items():
                writer.add_scalar(tag, value, int(point["step"]))

    def finish(self, cell: CellInfo, final: dict[str, float], step: int, error: str | None) -> None:
        from torch.utils.tensorboard.summary import hparams

        writer = self.writers.pop(cell.cell_id)
        for key, value in final.items():
            writer.add_scalar(metric_name(key), value, step)
        if error is not None:
            writer.add_text("error", error, step)
        # The session's end: HParams shows it done (or failed). hparams() gives the end as its third summary.
        *_, end = hparams({"cell_id": cell.cell_id}, {})
        if error is not None:
            end.value[0].metadata.plugin_data.content = _failed_end()
        writer.file_writer.add_summary(end)
        writer.close()

    def close(self, interrupted: bool) -> None:
        for writer in self.writers.values():
            writer.close()
        self.writers.clear()


def _failed_end() -> bytes:
    from tensorboard.plugins.hparams.api_pb2 import Status
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData, SessionEndInfo

    end = SessionEndInfo(status=Status.Value("STATUS_FAILURE"))
    return HParamsPluginData(session_end_info=end, version=0).SerializeToString()


def last_step(logdir: Path) -> int | None:
    """The largest scalar step in a run directory's event files (TensorBoard's own reader), or None."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(logdir), size_guidance={"scalars": 0})
    acc.Reload()
    steps = [e.step for tag in acc.Tags().get("scalars", []) for e in acc.Scalars(tag)]
    return max(steps) if steps else None
