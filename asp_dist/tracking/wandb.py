"""Weights & Biases: one W&B run per cell in the project (--wandb-project, WANDB_PROJECT, else "asp-dist"),
id = the cell id (a resumed cell continues its run), name "<treatment> paired=N trial=T", group = the
condition (domain/condition), job type = the treatment, tags = trial, sweep, code revision; config = the
resolved spec; history = the curve points at their update step; summary = the final eval/ metrics.

W&B's mode is the user's (WANDB_MODE); without one and without W&B credentials the runs are written offline
under DIR/wandb (``wandb sync DIR/wandb/offline-run-*`` uploads them later), so a sweep never waits on the
network or a login prompt. Online, the check logs in (W&B's own, verified against the server) within
--connect-timeout, and each cell's ``wandb.init`` waits at most that long (``init_timeout``). A resumed cell's
last step is read back from its run files (W&B's LevelDB-log records, W&B's own protobuf messages:
``history_steps``).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any, Iterator

from asp_dist.hashing import stable_hash
from asp_dist.tracking.base import (NoAnswer, Tracker, TrackerError, TrackingSettings, answer_within, first_line,
                                   hparam, metric_name, scalars)
from asp_dist.tracking.cells import CellInfo

LOCAL_MODES = ("offline", "dryrun", "disabled")  # W&B modes that do not reach a server


def _mode() -> str:
    if os.environ.get("WANDB_MODE"):
        return os.environ["WANDB_MODE"]
    has_key = os.environ.get("WANDB_API_KEY") or (Path.home() / ".netrc").is_file() and \
        "api.wandb.ai" in (Path.home() / ".netrc").read_text(errors="replace")
    return "online" if has_key else "offline"


class WandbTracker(Tracker):
    kind = "wandb"
    module = "wandb"
    install = "wandb"
    subdir = "wandb"  # W&B's own: wandb.init(dir=DIR) writes its runs under DIR/wandb

    def __init__(self, settings: TrackingSettings, sweep: str):
        super().__init__(settings, sweep)
        self.runs: dict[str, Any] = {}
        self.mode = _mode()

    @classmethod
    def check(cls, settings: TrackingSettings) -> None:
        super().check(settings)
        if _mode() in LOCAL_MODES:
            return
        import wandb

        where = os.environ.get("WANDB_BASE_URL") or "W&B's server"
        try:  # W&B's own login check, verified against the server; never a prompt
            logged_in = answer_within(settings.timeout_s, lambda: wandb.login(verify=True, prompt=False))
        except NoAnswer:
            raise TrackerError(f"--logger wandb: {where} did not answer within {settings.timeout_s:g} s; check "
                               f"WANDB_BASE_URL and the network, raise --connect-timeout, or set "
                               f"WANDB_MODE=offline") from None
        except Exception as e:  # noqa: BLE001 - whatever W&B raises for a server or key it cannot use
            raise TrackerError(f"--logger wandb: cannot log in to {where} ({first_line(e)}); or set "
                               f"WANDB_MODE=offline") from None
        if not logged_in:
            raise TrackerError("--logger wandb: W&B online mode needs credentials (WANDB_API_KEY or `wandb login`); "
                               "or set WANDB_MODE=offline")

    def open_cell(self, cell: CellInfo) -> int | None:
        import wandb

        run_id = run_id_of(cell)
        last = max((s for f in run_files(self.root, cell) for s in history_steps(f)), default=None)
        config = {k: hparam(v) for k, v in cell.config.items()} | {"sweep": cell.sweep, "cell_id": cell.cell_id,
                                                                   "code_revision": cell.revision}
        self.runs[cell.cell_id] = wandb.init(
            project=self.settings.wandb_project, dir=self.settings.dir, mode=self.mode, id=run_id, resume="allow",
            name=cell.run_name, group=cell.group, job_type=cell.treatment, config=config,
            tags=[f"trial={cell.trial}", f"sweep={cell.sweep}", f"rev={cell.revision[:12]}"],
            reinit="create_new", settings=wandb.Settings(console="off", x_disable_stats=True, silent=True,
                                                         **self._timeout()))
        return last

    def _timeout(self) -> dict[str, float]:
        """Online, a cell's init waits --connect-timeout for the server (W&B's default: 90 s); offline, W&B's."""
        return {} if self.mode in LOCAL_MODES else {"init_timeout": float(self.settings.timeout_s)}

    def log(self, cell: CellInfo, points: list[dict[str, Any]]) -> None:
        run = self.runs[cell.cell_id]
        for point in points:
            run.log(scalars(point), step=int(point["step"]))

    def finish(self, cell: CellInfo, final: dict[str, float], step: int, error: str | None) -> None:
        run = self.runs.pop(cell.cell_id)
        run.summary.update({metric_name(k): v for k, v in final.items()})
        if error is not None:
            run.summary["error"] = error[:2000]
        run.finish(exit_code=1 if error is not None else 0)

    def close(self, interrupted: bool) -> None:
        for run in self.runs.values():
            run.finish(exit_code=255 if interrupted else 0)
        self.runs.clear()


def run_id_of(cell: CellInfo) -> str:
    """The cell's W&B run id: the same on every run of the sweep, another in another sweep of the project."""
    return f"{cell.domain[:16]}-{stable_hash(f'{cell.sweep}/{cell.cell_id}')[:16]}"


def run_files(root: Path, cell: CellInfo) -> list[Path]:
    """The cell's W&B run files under ``root`` (DIR/wandb), oldest first: one per run of the sweep that logged
    it (W&B names a run's directory by its start second and id)."""
    run_id = run_id_of(cell)
    return sorted(root.glob(f"*-{run_id}/run-{run_id}.wandb"))


# ---- W&B's run files, read back ---------------------------------------------------------------
_BLOCK = 32768  # LevelDB log: 32 KiB blocks of records, each with a 7-byte header (crc, length, type)
_HEADER = 7  # W&B's file header: ":W&B", a 2-byte magic, a version byte


def records(path: Path) -> Iterator[Any]:
    """The protobuf Records (wandb.proto.wandb_internal_pb2.Record) of a run's .wandb file. A record cut short at
    the end (the file of a killed process, the case of a resumed cell) ends the file, as in a LevelDB log reader:
    the records before it are whole. A record that does not parse elsewhere raises protobuf's DecodeError (on a
    resume the hub then switches the tracker off with a warning, rather than resend the curve into the run)."""
    from wandb.proto import wandb_internal_pb2

    data = path.read_bytes()
    if not data.startswith(b":W&B"):
        raise ValueError(f"{path} is not a W&B run file")
    pos, parts = _HEADER, []
    while pos + 7 <= len(data):
        left = _BLOCK - pos % _BLOCK
        if left < 7:  # the block's tail is padding
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if kind == 0 and length == 0:
            pos += left  # zeroed rest of a block
            continue
        if pos + 7 + length > len(data):  # the torn tail of a killed writer
            return
        parts.append(data[pos + 7:pos + 7 + length])
        pos += 7 + length
        if kind in (1, 4):  # FULL or LAST: a record is whole
            record = wandb_internal_pb2.Record()
            record.ParseFromString(b"".join(parts))
            parts = []
            yield record


def history_steps(path: Path) -> list[int]:
    """The steps of a run file's history rows (what its run holds, by step)."""
    try:
        return [r.history.step.num for r in records(path) if r.WhichOneof("record_type") == "history"]
    except (OSError, ValueError):
        return []
