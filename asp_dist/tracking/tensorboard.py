"""TensorBoard: one run directory per cell under DIR/tensorboard/, its path the cell's group
(domain/condition/treatment/paired=N/trial=T-<id>), so TensorBoard's run filter finds a condition, a method
or a paired count by prefix. Scalars in sections (loss/, probe/, discriminator/, schedule/, eval/); the
resolved spec as HParams (with the trial, sweep and code revision), its metrics the cell's eval/ scalars.

Written with TensorBoard's own EventFileWriter (its event format, no TensorFlow or torch), one event per curve
point, flushed every few seconds so that a running ``tensorboard --logdir DIR/tensorboard`` shows the curves
while the cells train. A resumed cell
continues its directory: the last step it holds is read back with TensorBoard's EventAccumulator.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from asp_dist.tracking.base import Tracker, TrackingSettings, hparam, metric_name, scalars
from asp_dist.tracking.cells import CellInfo

FLUSH_SECS = 5  # how stale a live TensorBoard may be
PLUGIN = "hparams"  # TensorBoard's HParams plugin: its summaries, as torch.utils.tensorboard writes them


class TensorBoardTracker(Tracker):
    kind = "tensorboard"
    module = "tensorboard"
    install = "tensorboard"
    subdir = "tensorboard"

    def __init__(self, settings: TrackingSettings, sweep: str):
        super().__init__(settings, sweep)
        self.writers: dict[str, Any] = {}

    def logdir(self, cell: CellInfo) -> Path:
        return self.root / cell.run_path

    def open_cell(self, cell: CellInfo) -> int | None:
        from tensorboard.summary.writer.event_file_writer import EventFileWriter

        where = self.logdir(cell)
        last = last_step(where) if where.is_dir() else None
        where.mkdir(parents=True, exist_ok=True)
        writer = EventFileWriter(str(where), flush_secs=FLUSH_SECS)
        self.writers[cell.cell_id] = writer
        if last is None:  # a new run: its HParams once (a resumed run has them in its first event file)
            config = {k: hparam(v) for k, v in cell.config.items() if v is not None}
            config.update(sweep=cell.sweep, code_revision=cell.revision, cell_id=cell.cell_id,
                          condition=cell.condition, treatment=cell.treatment)
            for summary in hparams_start(config, [metric_name(f"eval_{m}") for m in cell.metrics]):
                writer.add_event(_event(0, summary))
        return last

    def log(self, cell: CellInfo, points: list[dict[str, Any]]) -> None:
        writer = self.writers[cell.cell_id]
        for point in points:  # one event per point, all its scalars in one summary
            writer.add_event(_event(int(point["step"]), _scalars(scalars(point))))

    def finish(self, cell: CellInfo, final: dict[str, float], step: int, error: str | None) -> None:
        writer = self.writers.pop(cell.cell_id)
        if final:
            writer.add_event(_event(step, _scalars({metric_name(k): v for k, v in final.items()})))
        if error is not None:
            writer.add_event(_event(step, _text("error", error)))
        writer.add_event(_event(step, hparams_end(failed=error is not None)))  # HParams shows the session done
        writer.close()

    def close(self, interrupted: bool) -> None:
        for writer in self.writers.values():
            writer.close()
        self.writers.clear()


# ---- TensorBoard's protos, written directly (no TensorFlow, no torch; what torch.utils.tensorboard writes) ----
def _event(step: int, summary) -> Any:
    from tensorboard.compat.proto.event_pb2 import Event

    return Event(wall_time=time.time(), step=step, summary=summary)


def _scalars(values: dict[str, float]) -> Any:
    from tensorboard.compat.proto.summary_pb2 import Summary

    return Summary(value=[Summary.Value(tag=tag, simple_value=v) for tag, v in values.items()])


def _text(tag: str, text: str) -> Any:
    from tensorboard.compat.proto.summary_pb2 import Summary, SummaryMetadata
    from tensorboard.compat.proto.tensor_pb2 import TensorProto
    from tensorboard.compat.proto.tensor_shape_pb2 import TensorShapeProto

    meta = SummaryMetadata(plugin_data=SummaryMetadata.PluginData(plugin_name="text"))
    tensor = TensorProto(dtype=7, string_val=[text.encode()], tensor_shape=TensorShapeProto(dim=[]))  # 7: DT_STRING
    return Summary(value=[Summary.Value(tag=tag, metadata=meta, tensor=tensor)])


def _plugin_summary(tag: str, content: Any) -> Any:
    from tensorboard.compat.proto.summary_pb2 import Summary, SummaryMetadata

    meta = SummaryMetadata(plugin_data=SummaryMetadata.PluginData(plugin_name=PLUGIN,
                                                                  content=content.SerializeToString()))
    return Summary(value=[Summary.Value(tag=tag, metadata=meta)])


def hparams_start(config: dict[str, Any], metrics: list[str]) -> list[Any]:
    """The experiment and session-start summaries of the HParams plugin: the config as hparams, `metrics` the
    scalar tags its table shows."""
    from tensorboard.plugins.hparams.api_pb2 import DataType, Experiment, HParamInfo, MetricInfo, MetricName
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData, SessionStartInfo

    start, infos = SessionStartInfo(), []
    for name, value in config.items():
        if isinstance(value, bool):
            start.hparams[name].bool_value, kind = value, "DATA_TYPE_BOOL"
        elif isinstance(value, (int, float)):
            start.hparams[name].number_value, kind = float(value), "DATA_TYPE_FLOAT64"
        else:
            start.hparams[name].string_value, kind = str(value), "DATA_TYPE_STRING"
        infos.append(HParamInfo(name=name, type=DataType.Value(kind)))
    experiment = Experiment(hparam_infos=infos, metric_infos=[MetricInfo(name=MetricName(tag=m)) for m in metrics])
    return [_plugin_summary("_hparams_/experiment", HParamsPluginData(experiment=experiment, version=0)),
            _plugin_summary("_hparams_/session_start_info", HParamsPluginData(session_start_info=start, version=0))]


def hparams_end(failed: bool) -> Any:
    from tensorboard.plugins.hparams.api_pb2 import Status
    from tensorboard.plugins.hparams.plugin_data_pb2 import HParamsPluginData, SessionEndInfo

    end = SessionEndInfo(status=Status.Value("STATUS_FAILURE" if failed else "STATUS_SUCCESS"))
    return _plugin_summary("_hparams_/session_end_info", HParamsPluginData(session_end_info=end, version=0))


def last_step(logdir: Path) -> int | None:
    """The largest scalar step in a run directory's event files (TensorBoard's own reader), or None."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(logdir), size_guidance={"scalars": 0})
    acc.Reload()
    steps = [e.step for tag in acc.Tags().get("scalars", []) for e in acc.Scalars(tag)]
    return max(steps) if steps else None
