"""What every tracker is: the settings they share, the names of what they log, and the Tracker class.

A tracker gets a cell's curve points while it trains and its final metrics when it ends, one tracker run per
cell (asp_dist.tracking.cells.CellInfo says how it is named and grouped). The hub (asp_dist.tracking.hub)
calls it; a tracker never sees a point twice for the same step, also across a resume: ``open_cell`` says
which step the cell's run already holds, read back from the tracker's own storage.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, ClassVar, TypeVar

from asp_dist.errors import SpecError
from asp_dist.tracking.cells import CellInfo


# The error a cell's run ends with when the sweep stopped (or its worker died for good) before the cell ended.
STOPPED = "stopped before the cell finished (the sweep was interrupted or its worker died); resume continues it"


class TrackerError(SpecError):
    """A logger that cannot start: one line `asp-dist: error: …`, before anything runs."""


@dataclass(frozen=True)
class TrackingSettings:
    """Which trackers a sweep run feeds, and where (the flags --logger, --logger-dir, --mlflow-uri,
    --wandb-project, or a space file's [logging] table)."""

    loggers: tuple[str, ...] = ()  # tensorboard | mlflow | wandb | json, in the order given
    dir: str | None = None  # where file-based trackers write (default: RESULTS/NAME/trackers)
    mlflow_uri: str | None = None  # MLflow tracking URI (default: MLFLOW_TRACKING_URI, else sqlite:///DIR/mlflow.db)
    wandb_project: str | None = None  # W&B project (default: WANDB_PROJECT, else "asp-dist")
    # --connect-timeout: how long a tracker's server has to answer the check, and what bounds each of its calls
    # during the sweep (MLflow's HTTP timeout, W&B's init_timeout). A run option, not recorded in tracking.json.
    timeout_s: float = 20.0

    def resolved(self, default_dir: str | Path) -> "TrackingSettings":
        """Every default filled in: the directory, the MLflow URI, the W&B project."""
        where = Path(self.dir if self.dir is not None else default_dir).absolute()
        uri = self.mlflow_uri or os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{where / 'mlflow.db'}"
        project = self.wandb_project or os.environ.get("WANDB_PROJECT") or "asp-dist"
        return replace(self, dir=str(where), mlflow_uri=uri, wandb_project=project)

    def to_dict(self) -> dict[str, Any]:
        return {"loggers": list(self.loggers), "dir": self.dir, "mlflow_uri": self.mlflow_uri,
                "wandb_project": self.wandb_project}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrackingSettings":
        return cls(tuple(d.get("loggers", ())), d.get("dir"), d.get("mlflow_uri"), d.get("wandb_project"))


def metric_name(key: str) -> str:
    """A curve point's or row's key as trackers show it, in sections: loss/paired, probe/mixed,
    discriminator/acc_real, schedule/lambda_unpaired, eval/mixed."""
    for prefix, section in (("loss_", "loss"), ("probe_", "probe"), ("eval_", "eval"), ("disc_", "discriminator")):
        if key.startswith(prefix):
            return f"{section}/{key.removeprefix(prefix)}"
    if key == "d_fake":
        return "discriminator/d_fake"
    if key == "lambda_unpaired_now":
        return "schedule/lambda_unpaired"
    return key


def scalars(point: dict[str, Any]) -> dict[str, float]:
    """A point's numbers by tracker name, without its step (and without what is not a finite-or-not float)."""
    return {metric_name(k): float(v) for k, v in point.items()
            if k != "step" and isinstance(v, (int, float)) and not isinstance(v, bool)}


def hparam(value: Any) -> Any:
    """A spec value as a tracker's parameter accepts it: numbers, strings and bools as they are, else text."""
    return value if isinstance(value, (int, float, str, bool)) else str(value)


def check_writable(kind: str, where: Path) -> None:
    """The tracker's directory is writable or can be made (else TrackerError). Creates nothing: the check runs
    before the sweep's own directory is made."""
    probe = where.absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        what = "is not a directory" if not probe.is_dir() else "is not writable"
        raise TrackerError(f"--logger {kind}: cannot write to {where} ({probe} {what}); pass a writable --logger-dir")


_T = TypeVar("_T")


class NoAnswer(Exception):
    """A call given up on by ``answer_within``."""


def answer_within(seconds: float, call: Callable[[], _T]) -> _T:
    """``call()``'s result or exception, or NoAnswer once `seconds` pass without either. The call runs in a daemon
    thread: a client library's own timeouts and retries (or a resolver) cannot hold the check longer, and a call
    still hanging when the process exits does not keep it alive."""
    answer: list[tuple[bool, Any]] = []

    def run() -> None:
        try:
            answer.append((True, call()))
        except BaseException as e:  # noqa: BLE001 - handed to the caller
            answer.append((False, e))

    thread = threading.Thread(target=run, name="asp-dist-tracker-check", daemon=True)
    thread.start()
    thread.join(seconds)
    if not answer:
        raise NoAnswer(f"no answer within {seconds:g} s")
    ok, value = answer[0]
    if not ok:
        raise value
    return value


def first_line(e: BaseException, limit: int = 200) -> str:
    text = str(e).strip()
    return (text.splitlines()[0] if text else type(e).__name__)[:limit]


class Tracker:
    """One kind of tracker. Subclasses set ``kind`` and ``module`` and write the methods below; every
    method may raise (the hub turns a failure into one warning and switches that tracker off)."""

    kind: ClassVar[str]
    module: ClassVar[str]  # the library it needs (its import is the check that it is installed)
    install: ClassVar[str]  # what to pip install when it is missing
    subdir: ClassVar[str | None] = None  # its directory under the tracker directory, if it writes files there

    def __init__(self, settings: TrackingSettings, sweep: str):
        self.settings, self.sweep = settings, sweep

    @property
    def root(self) -> Path:
        """Where it writes: DIR/<subdir>."""
        return Path(self.settings.dir) / (self.subdir or "")

    @classmethod
    def check(cls, settings: TrackingSettings) -> None:
        """Refuse, in one TrackerError line, a tracker that cannot start (library missing, unwritable
        directory, bad URI). Settings are resolved."""
        import importlib

        try:
            importlib.import_module(cls.module)
        except ImportError as e:
            raise TrackerError(f"--logger {cls.kind} needs {cls.module} ({e}); pip install {cls.install}") from None
        if cls.subdir is not None:
            check_writable(cls.kind, Path(settings.dir) / cls.subdir)

    def start(self) -> None:
        """Once per sweep run, before the first cell."""

    def open_cell(self, cell: CellInfo) -> int | None:
        """Start (or continue) the cell's run; the last step it already holds (None: a new run)."""
        raise NotImplementedError

    def log(self, cell: CellInfo, points: list[dict[str, Any]]) -> None:
        """Curve points, steps increasing, each newer than what the run holds."""
        raise NotImplementedError

    def finish(self, cell: CellInfo, final: dict[str, float], step: int, error: str | None) -> None:
        """The cell ended: its final metrics at `step` (its last update), or the error it failed with."""
        raise NotImplementedError

    def close(self, interrupted: bool) -> None:
        """The sweep run ends (interrupted: stopped before every cell finished)."""
