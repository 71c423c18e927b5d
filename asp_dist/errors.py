"""The errors a user can cause. The CLI prints any of them as one line and exits 2.

They live below every other module so that any stage can raise them without importing a
stage above it.
"""

from __future__ import annotations


class SpecError(ValueError):
    """A cell spec, space file or flag that cannot run; the message says what to fix."""


class SweepError(SpecError):
    """A sweep that cannot start or continue (name, results tree, grid, lock)."""


class SchemaError(SpecError):
    """Result rows whose columns do not match the pinned row schema (asp_dist.training.row)."""


class StorageError(SweepError):
    """Object storage that cannot be used as asked: an endpoint that does not answer, refused
    credentials, a missing bucket (asp_dist.results.location). One line, exit 2, like any SweepError;
    inside a running cell it is a crash (retried), never a deterministic failure of the cell."""
