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
    credentials, a missing bucket (asp_dist.results.s3). One line, exit 2, like any SweepError;
    inside a running cell it is a crash (retried), never a deterministic failure of the cell."""


class DiskFull(SweepError):
    """A write that found no space left (ENOSPC) or no quota (EDQUOT): the sweep stops, finished cells stay,
    and `resume` continues once there is room. One line, exit 2."""


def is_disk_full(err: BaseException) -> bool:
    """An OSError of a full disk or quota, also as pyarrow words it ("[errno 28] No space left on device")."""
    import errno

    return isinstance(err, OSError) and (err.errno in (errno.ENOSPC, errno.EDQUOT) or "No space left on device"
                                         in str(err) or "Disk quota exceeded" in str(err))
