"""Where a sweep's results live: a local directory (a plain ``pathlib.Path``) or a prefix in an
S3-compatible bucket (``S3Path``, asp_dist.results.s3), resolved from the ``--results`` string.

``as_path("results")`` is ``Path("results")`` — the local path stays the default and keeps every
code path it had. ``as_path("s3://bucket/prefix")`` is an ``S3Path``, with the part of the ``pathlib``
API the store uses, so the store's layout code reads the same for both. What differs by kind is here,
written once for either: a write that never overwrites (``write_table_once``: a hard link locally, a
conditional PUT on S3), an atomic replace, a move aside, and Parquet footers, schemas and datasets.
Everything specific to S3 (its clients, errors, bucket check and ``S3Path`` itself) is in
asp_dist.results.s3.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence, Union

from asp_dist.results.s3 import S3_SCHEME, S3Path, filesystem, storage_error

if TYPE_CHECKING:
    import pyarrow as pa
    import pyarrow.dataset as ds


def is_remote(path: Any) -> bool:
    """True for an S3Path or an ``s3://`` string."""
    return isinstance(path, S3Path) or (isinstance(path, str) and path.startswith(S3_SCHEME))


def as_path(path: str | os.PathLike | S3Path) -> Path | S3Path:
    """``s3://bucket/prefix`` as an S3Path; anything else as the local Path it always was."""
    if isinstance(path, S3Path):
        return path
    if isinstance(path, str) and path.startswith(S3_SCHEME):
        return S3Path.from_uri(path)
    return Path(path)


AnyPath = Union[Path, S3Path]


# ---- writes and Parquet for either kind ----------------------------------------------------------------
def parquet_bytes(table: pa.Table) -> bytes:
    import pyarrow as pa
    import pyarrow.parquet as pq

    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def write_table_once(table: pa.Table, final: AnyPath) -> bool:
    """A table written once under `final`, never overwritten (False if it exists): a hard link on a
    local disk (asp_dist.fsutil), a conditional PUT on S3."""
    if isinstance(final, S3Path):
        return final.create(parquet_bytes(table))
    from asp_dist.fsutil import link_table_once

    return link_table_once(table, final)


def write_replace(path: AnyPath, data: bytes | str) -> None:
    """Replace `path` with `data` atomically: temp file + rename locally, one PUT on S3."""
    if isinstance(path, S3Path):
        path.write_bytes(data.encode() if isinstance(data, str) else data)
        return
    from asp_dist.fsutil import atomic_write

    atomic_write(path, data)


def move_aside(path: AnyPath, dest: AnyPath) -> None:
    """Move `path` to `dest` (a new name): a rename on a local disk (a symbolic link moves as the link), a
    copy then a delete on S3 (a reader may see both for a moment, never neither)."""
    if isinstance(path, S3Path):
        dest.write_bytes(path.read_bytes())
        path.unlink(missing_ok=True)
        return
    Path(dest).parent.mkdir(parents=True, exist_ok=True)
    os.replace(path, dest)


def parquet_file(path: AnyPath):
    """pyarrow.parquet.ParquetFile of a local path or an S3 object."""
    import pyarrow.parquet as pq

    if isinstance(path, S3Path):
        return pq.ParquetFile(path.open_input())
    return pq.ParquetFile(path)


def parquet_metadata(path: AnyPath):
    """The footer (pyarrow.parquet.FileMetaData) of a local path or an S3 object, nothing else read."""
    import pyarrow.parquet as pq

    if isinstance(path, S3Path):
        with path.open_input() as fh:
            return pq.read_metadata(fh)
    return pq.read_metadata(path)


def read_parquet_schema(path: AnyPath) -> pa.Schema:
    import pyarrow.parquet as pq

    if isinstance(path, S3Path):
        with path.open_input() as fh:
            return pq.read_schema(fh)
    return pq.read_schema(path)


def parquet_dataset(files: Sequence[AnyPath], schema: pa.Schema | None = None) -> ds.Dataset:
    """One pyarrow dataset over exactly these files, local or on S3 (a union when both)."""
    import pyarrow.dataset as ds

    local = [str(f) for f in files if not isinstance(f, S3Path)]
    remote = [f.fs_path for f in files if isinstance(f, S3Path)]
    if not remote:
        return ds.dataset(local, schema=schema, format="parquet")
    try:
        on_s3 = ds.dataset(remote, schema=schema, format="parquet", filesystem=filesystem())
    except OSError as err:
        raise storage_error(err, str(files[0])) from None
    if not local:
        return on_s3
    return ds.dataset([ds.dataset(local, schema=schema, format="parquet"), on_s3])

