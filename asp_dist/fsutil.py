"""Crash-safe file writes: readers see the old file or the new one, never half of one (or of a set of files)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq


def link_table_once(table: pa.Table, final: Path) -> bool:
    """Write `table` to `final` through a hidden temp file and an atomic link; never overwrites.
    Returns False (and writes nothing) if `final` already exists."""
    final = Path(final)
    if final.exists():
        return False
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=".tmp", dir=final.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        try:
            os.link(tmp, final)  # atomic and never overwrites: a racing writer loses cleanly
        except FileExistsError:
            return False
        except OSError:
            # Filesystems without hard links: rename is still atomic (last writer wins; rows are equal).
            os.replace(tmp, final)
            return True
        return True
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write(path: Path, data: bytes | str) -> None:
    """Replace `path` with `data` through a hidden temp file, fsync and rename: readers see the
    old file or the new one, never half of it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data.encode() if isinstance(data, str) else data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


@contextmanager
def staged_directory(final: Path) -> Iterator[Path]:
    """A fresh directory to write a set of files into, moved into `final` only when the block succeeds: a
    block that fails (a full disk, an error, Ctrl-C) leaves `final` exactly as it was.

    The stage is a hidden folder inside `final` (same filesystem: every move is a rename), and its last part
    has `final`'s name, so that paths relative to it and its name read as they will in `final`."""
    final = Path(final)
    holder = Path(tempfile.mkdtemp(prefix=".staging-", dir=final))
    stage = holder / (final.name or final.resolve().name or "out")
    stage.mkdir()
    try:
        yield stage
        move_files_into(stage, final, backup=holder / ".replaced")
    finally:
        shutil.rmtree(holder, ignore_errors=True)


def move_files_into(src: Path, dest: Path, backup: Path) -> None:
    """Every file under `src` renamed to the same place under `dest`, replacing any there; all or nothing:
    replaced files wait in `backup` until the last rename, and a failed rename puts every earlier one back."""
    done: list[tuple[Path, Path | None]] = []  # (target, its old file in backup, or None)
    made: list[Path] = []  # directories created under dest
    try:
        for path in sorted(p for p in src.rglob("*") if not p.is_dir()):
            rel = path.relative_to(src)
            target = dest / rel
            for parent in reversed(rel.parents[:-1]):  # stats/, figures/: shallowest first
                if not (dest / parent).is_dir():
                    (dest / parent).mkdir()
                    made.append(dest / parent)
            old = None
            if target.exists() or target.is_symlink():
                old = backup / rel
                old.parent.mkdir(parents=True, exist_ok=True)
                os.replace(target, old)
            done.append((target, old))
            os.replace(path, target)
    except BaseException:
        for target, old in reversed(done):
            if old is not None:
                os.replace(old, target)
            else:
                target.unlink(missing_ok=True)
        for directory in reversed(made):
            directory.rmdir()
        raise
