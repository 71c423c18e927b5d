"""What a sweep run is given: a Plan (which cells, under which name, and the sweep's manifest as the checks read
it) read and resolved once, and the RunOptions of how to run them. The CLI builds both, checks them before Ray is
imported, and hands them to sweep.tune.run_plan; nothing downstream expands the space again, and the run reads
the manifest once more only under the sweep's lock (where it may have changed since)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from asp_dist.results import store
from asp_dist.spec import CellSpec
from asp_dist.sweep import ledger, preflight
from asp_dist.sweep.packing import check_packing
from asp_dist.sweep.spaces import expand, space_file, space_logging
from asp_dist.tracking.base import TrackingSettings

DEFAULT_MAX_FAILURES = 2
DEFAULT_CHECKPOINT_EVERY_S = 30.0


@dataclass(frozen=True)
class RunOptions:
    """How a sweep runs (the flags of `sweep` and `resume`)."""

    results: str | Path = store.DEFAULT_RESULTS  # results root: a directory or s3://bucket/prefix
    workers: int = 2  # embedded Ray: CPU workers (one cell, or one pack, each)
    address: str | None = None  # a running Ray cluster to join instead (host:port)
    max_failures: int = DEFAULT_MAX_FAILURES  # retries of a trial whose worker died
    checkpoint_every_s: float = DEFAULT_CHECKPOINT_EVERY_S  # a running cell checkpoints this often
    ray_temp_dir: str | None = None  # the embedded Ray's temp dir (default: ASP_DIST_RAY_TEMP_DIR or Ray's)
    dashboard: bool = False  # the embedded Ray's dashboard (127.0.0.1 only)
    connect_timeout_s: float = ledger.DEFAULT_CONNECT_TIMEOUT_S  # a cluster's (and S3's) first answer
    pack: str | None = None  # --pack: how cells are grouped into Tune trials (None: the sweep's own)
    pack_size: int | None = None
    tracking: TrackingSettings = TrackingSettings()  # live trackers (--logger ...; none by default)
    extend: bool = False  # --extend: a grid that adds cells to the stored one grows the sweep

    def check(self) -> None:
        """The numbers and the packing, refused in one line before anything is read or written."""
        preflight.check_run_options(self.workers, self.max_failures, self.checkpoint_every_s, self.connect_timeout_s)
        check_packing(self.pack, self.pack_size)


@dataclass(frozen=True)
class Plan:
    """The cells of one sweep run: its name, the space it came from and the resolved specs."""

    name: str
    space: str  # the space's name (a file's stem), as the manifest records it
    specs: list[CellSpec]
    space_text: str | None = None  # the space file as read (None: a resume from the manifest)
    logging: dict = field(default_factory=dict)  # the space file's [logging] table (asp_dist.sweep.spaces)
    # The sweep's manifest as the checks before the run read it (None: a new sweep; preflight.UNREAD: not read)
    manifest: Any = preflight.UNREAD

    @classmethod
    def from_space(cls, space: str, name: str | None = None) -> "Plan":
        """A new (or continued) sweep of a space: tune_spaces/<space>.toml or a path."""
        path = space_file(space)
        return cls(name if name is not None else path.stem, path.stem, expand(space), path.read_text(),
                   space_logging(space))

    @classmethod
    def from_sweep(cls, results: str | Path, name: str) -> "Plan":
        """An existing sweep, from its manifest (no space file needed)."""
        _, manifest = ledger.read_sweep(results, name)
        return cls.from_manifest(name, manifest)

    @classmethod
    def from_manifest(cls, name: str, manifest: dict) -> "Plan":
        """An existing sweep, from its manifest as read (preflight.check_can_resume)."""
        return cls(name, manifest["space"], ledger.specs_from_manifest(manifest), manifest=manifest)
