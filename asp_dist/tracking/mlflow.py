"""MLflow: an experiment per sweep (its name), one parent run per sweep and a nested run per cell
(``mlflow.parentRunId``), named "<treatment> paired=N trial=T"; params = the resolved spec; tags = the
cell's group (domain, condition, method, treatment, paired, trial), sweep and code revision; metrics = the
curve points at their update step and the final eval/ metrics at the last step.

Through MlflowClient on any tracking URI: by default a SQLite store in the tracker directory (MLflow's
recommended local backend; its file store is in maintenance mode), or MLFLOW_TRACKING_URI / --mlflow-uri
(a server, a database). A resumed sweep finds its parent run and each cell's run by tag and continues them:
the last step a cell's run holds is read back from its metric histories.

A server that does not answer is given up on in bounded time. The check (before anything runs) waits
--connect-timeout for its answer. During the sweep each client call is bounded by MLflow's HTTP settings, set
in the hub's process unless the user set them: a request times out after --connect-timeout and is retried twice
(MLflow's defaults, 120 s and 7 retries with backoff, hold a call for minutes), so a server that goes away
holds the hub for at most about 3 x --connect-timeout before the tracker is switched off.
"""

from __future__ import annotations

import math
import os
import re
import time
from typing import Any

from asp_dist.tracking.base import (STOPPED, NoAnswer, Tracker, TrackerError, TrackingSettings, answer_within,
                                   check_writable, first_line, hparam, metric_name, scalars)
from asp_dist.tracking.cells import CellInfo

ROLE, SWEEP, CELL = "asp_dist.role", "asp_dist.sweep", "asp_dist.cell_id"
PARENT = "mlflow.parentRunId"
BATCH = 900  # metrics per log_batch call (MLflow allows 1,000)
SWEEP_RETRIES = 2  # retries of an HTTP request during the sweep (the check makes one try)


def bound_http(timeout_s: float, retries: int) -> list[str]:
    """Bound each MLflow HTTP request in this process: `timeout_s` (rounded up; MLflow takes whole seconds) to
    connect and to read, `retries` retries one second apart, then twice that. Only the variables the user has
    not set; returns the ones set here."""
    bounds = {"MLFLOW_HTTP_REQUEST_TIMEOUT": str(max(1, math.ceil(timeout_s))),
              "MLFLOW_HTTP_REQUEST_MAX_RETRIES": str(retries), "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1"}
    added = [k for k in bounds if k not in os.environ]
    os.environ.update({k: bounds[k] for k in added})
    return added


def _quiet() -> None:
    """MLflow sets its loggers up when imported; its INFO lines (database migrations) would drown the sweep's
    progress line."""
    import logging

    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)


class MLflowTracker(Tracker):
    kind = "mlflow"
    module = "mlflow"
    install = "mlflow-skinny sqlalchemy alembic"

    def __init__(self, settings: TrackingSettings, sweep: str):
        super().__init__(settings, sweep)
        self.client = None
        self.parent: str | None = None
        self.runs: dict[str, str] = {}  # cell id -> run id (existing ones, found at start)

    @classmethod
    def check(cls, settings: TrackingSettings) -> None:
        super().check(settings)
        uri = settings.mlflow_uri
        if uri.startswith("sqlite:///"):  # made at start; its directory must take it, SQLAlchemy must be here
            from pathlib import Path

            check_writable(cls.kind, Path(uri.removeprefix("sqlite:///")).parent)
            try:
                import alembic  # noqa: F401
                import sqlalchemy  # noqa: F401
            except ImportError as e:
                raise TrackerError(f"--logger mlflow with {uri} needs SQLAlchemy and Alembic ({e}); "
                                   f"pip install sqlalchemy alembic") from None
            return
        # A server or a database: it answers within --connect-timeout, or the sweep does not start.
        from mlflow.tracking import MlflowClient

        _quiet()
        added = bound_http(settings.timeout_s, retries=0)
        try:
            answer_within(settings.timeout_s, lambda: MlflowClient(tracking_uri=uri).search_experiments(max_results=1))
        except NoAnswer:
            raise TrackerError(f"--logger mlflow: tracking URI {uri} did not answer within {settings.timeout_s:g} s; "
                               f"check --mlflow-uri, or raise --connect-timeout") from None
        except Exception as e:  # noqa: BLE001 - whatever MLflow raises for a URI it cannot use
            # MLflow wraps the OS's error in its own and requests' text: say the OS's when there is one
            errno = re.search(r"\[Errno -?\d+\] [^'\")\]]+", str(e))
            why = errno.group(0).strip() if errno else first_line(e)
            raise TrackerError(f"--logger mlflow: tracking URI {uri} cannot be used ({why})") from None
        finally:
            for key in added:
                os.environ.pop(key, None)

    def start(self) -> None:
        from mlflow.tracking import MlflowClient

        _quiet()
        if not self.settings.mlflow_uri.startswith("sqlite:"):  # a server: no call may hold the hub for minutes
            bound_http(self.settings.timeout_s, SWEEP_RETRIES)
        self.client = MlflowClient(tracking_uri=self.settings.mlflow_uri)
        experiment = self.client.get_experiment_by_name(self.sweep)
        self.experiment = (experiment.experiment_id if experiment is not None
                           else self.client.create_experiment(self.sweep))
        found = self.client.search_runs([self.experiment], f"tags.`{ROLE}` = 'sweep'", max_results=1)
        if found:
            self.parent = found[0].info.run_id
            self.client.update_run(self.parent, status="RUNNING")
        else:
            self.parent = self.client.create_run(self.experiment, run_name=self.sweep,
                                                 tags={ROLE: "sweep", SWEEP: self.sweep}).info.run_id
        token = None
        while True:  # the cells' runs of earlier runs of this sweep
            page = self.client.search_runs([self.experiment], f"tags.`{PARENT}` = '{self.parent}'",
                                           max_results=5000, page_token=token)
            self.runs.update({r.data.tags[CELL]: r.info.run_id for r in page if CELL in r.data.tags})
            token = page.token
            if not token:
                break

    def open_cell(self, cell: CellInfo) -> int | None:
        from mlflow.entities import Param, RunTag

        run_id = self.runs.get(cell.cell_id)
        if run_id is not None:  # a resumed cell: its run, and the last step it holds
            self.client.update_run(run_id, status="RUNNING")
            keys = self.client.get_run(run_id).data.metrics
            steps = [m.step for key in keys for m in self.client.get_metric_history(run_id, key)]
            return max(steps) if steps else None
        tags = {f"asp_dist.{k}": v for k, v in cell.tags.items()} | {PARENT: self.parent, CELL: cell.cell_id,
                                                                    "group": cell.group}
        run = self.client.create_run(self.experiment, run_name=cell.run_name, tags=tags)
        self.runs[cell.cell_id] = run.info.run_id
        params = [Param(k, str(hparam(v))) for k, v in sorted(cell.config.items())]
        for i in range(0, len(params), 100):  # MLflow takes 100 params per batch
            self.client.log_batch(run.info.run_id, params=params[i:i + 100])
        self.client.log_batch(run.info.run_id, tags=[RunTag("mlflow.note.content",
                                                            f"asp-dist cell {cell.cell_id} of sweep {cell.sweep}")])
        return None

    def _metrics(self, run_id: str, values: list[tuple[str, float, int]]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        metrics = [Metric(key, value, now, step) for key, value, step in values]
        for i in range(0, len(metrics), BATCH):
            self.client.log_batch(run_id, metrics=metrics[i:i + BATCH])

    def log(self, cell: CellInfo, points: list[dict[str, Any]]) -> None:
        self._metrics(self.runs[cell.cell_id], [(k, v, int(p["step"])) for p in points for k, v in scalars(p).items()])

    def finish(self, cell: CellInfo, final: dict[str, float], step: int, error: str | None) -> None:
        run_id = self.runs[cell.cell_id]
        self._metrics(run_id, [(metric_name(k), v, step) for k, v in final.items()])
        if error is not None:
            self.client.set_tag(run_id, "asp_dist.error", error[:5000])
        self.client.set_terminated(run_id, status="FINISHED" if error is None else "KILLED" if error == STOPPED
                                   else "FAILED")

    def close(self, interrupted: bool) -> None:
        if self.client is not None and self.parent is not None:
            self.client.set_terminated(self.parent, status="KILLED" if interrupted else "FINISHED")
