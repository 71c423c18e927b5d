"""Where Tune keeps a sweep's experiments, and, on object storage, a filesystem that uploads only what changed.

Tune's driver stages its experiment directory on local disk (its experiment state, and every trial's
``result.json``, ``progress.csv``, ``params.json`` and ``params.pkl``, written by its logger callbacks) and at
every sync uploads the whole directory again (``ray.train._internal.storage._upload_to_fs_path``). A sweep
forces a sync after every trial checkpoint (``CheckpointConfig(num_to_keep=1)``: what lets a killed driver
resume each cell from its latest checkpoint), so every checkpoint of a running cell re-sent the files of every
trial done so far: the requests grew as trials done × checkpoints taken. That was 9,500 of the 12,000
requests of the S3 kill test (docs/performance.md), and a real bucket bills each one.

On S3 the sweep hands Tune ``only_changed_uploads(fs)`` instead of the bare S3 filesystem: a write of bytes
equal to what this process last wrote at that path, or the creation of a directory it has already
created, is skipped; everything else passes through unchanged. Each process remembers only its own writes
(pickling drops the memory, so each worker starts empty), and any delete, move or copy through it forgets
the paths concerned. Only the sweep's own processes write under its ``tune/`` prefix while it runs (the
ledger's lease holds one driver at a time), so a skipped write is a file that is already there, byte for
byte. On local disk Tune's sync is a local copy, cheap enough to leave as it is.
"""

from __future__ import annotations

import hashlib
import io
import threading
from typing import Any

import pyarrow as pa
import pyarrow.fs as pafs

from asp_dist.results.location import AnyPath
from asp_dist.results.s3 import S3Path, filesystem

TUNE_DIR = "tune"
HELD_BYTES = 8 << 20  # a write up to this size is held and compared; a larger one (a big checkpoint) streams through


def tune_storage(sweep_dir: AnyPath) -> tuple[str, Any]:
    """Where Tune keeps the sweep's experiments: (storage_path, storage_filesystem). On S3 the path is
    ``bucket/prefix/<sweep>/tune`` on pyarrow's S3FileSystem (its endpoint from AWS_ENDPOINT_URL, its
    credentials from each node's AWS chain: the pickled filesystem carries none), seen through
    ``only_changed_uploads``."""
    if isinstance(sweep_dir, S3Path):
        return (sweep_dir / TUNE_DIR).fs_path, only_changed_uploads(filesystem(background_writes=False))
    return str(sweep_dir / TUNE_DIR), None


def only_changed_uploads(fs: pafs.FileSystem) -> pafs.PyFileSystem:
    """`fs` as a pyarrow filesystem that skips rewriting unchanged files and recreating directories."""
    return pafs.PyFileSystem(OnlyChangedUploads(fs))


def _under(path: str, root: str) -> bool:
    return path == root or path.startswith(root.rstrip("/") + "/")


class OnlyChangedUploads(pafs.FileSystemHandler):
    """The handler behind ``only_changed_uploads``: reads and listings go straight to the wrapped
    filesystem; writes are held in memory until closed and sent only when their bytes differ from this
    process's last write there. Thread-safe: pyarrow copies a directory on several threads of its IO pool, and
    the writes that do go out are sent one at a time, as Ray's own copy does for S3 (apache/arrow#32372). The
    wrapped S3 filesystem must write without background writes (``filesystem(background_writes=False)``): a
    write closed on an IO-pool thread that waits for that same pool deadlocks once every thread of it waits."""

    def __init__(self, fs: pafs.FileSystem):
        self.fs = fs
        self._lock = threading.Lock()  # guards the two memories below
        self._send = threading.Lock()  # one write to the wrapped filesystem at a time
        self._written: dict[str, bytes] = {}  # path -> digest of the bytes this process last wrote there
        self._dirs: set[str] = set()  # directories this process created

    def __reduce__(self):  # a worker gets the wrapped filesystem and a memory of its own
        return OnlyChangedUploads, (self.fs,)

    # ---- what is skipped -------------------------------------------------------------------------------
    def write_if_changed(self, path: str, data: bytes, metadata) -> bool:
        """Write `data` at `path` unless this process last wrote exactly these bytes there; True if written."""
        digest = hashlib.blake2b(data, digest_size=16).digest()
        with self._lock:
            if self._written.get(path) == digest:
                return False
            self._written.pop(path, None)  # unknown until this write has succeeded
        with self._send, self.fs.open_output_stream(path, metadata=metadata) as out:
            out.write(data)
        with self._lock:
            self._written[path] = digest
        return True

    def create_dir(self, path: str, recursive: bool) -> None:
        with self._lock:
            if path in self._dirs:
                return
        self.fs.create_dir(path, recursive=recursive)
        with self._lock:
            self._dirs.add(path)

    def forget(self, root: str) -> None:
        """Drop what is remembered at or under `root` (deleted, moved or overwritten by other means)."""
        with self._lock:
            self._written = {p: d for p, d in self._written.items() if not _under(p, root)}
            self._dirs = {p for p in self._dirs if not _under(p, root)}

    def open_output_stream(self, path: str, metadata) -> pa.NativeFile:
        return pa.PythonFile(_HeldWrite(self, path, metadata), mode="w")

    # ---- what changes the store: forget, then pass through -----------------------------------------------
    def open_append_stream(self, path: str, metadata) -> pa.NativeFile:
        self.forget(path)
        return self.fs.open_append_stream(path, metadata=metadata)

    def delete_dir(self, path: str) -> None:
        self.forget(path)
        self.fs.delete_dir(path)

    def delete_dir_contents(self, path: str, missing_dir_ok: bool = False) -> None:
        self.forget(path)
        self.fs.delete_dir_contents(path, missing_dir_ok=missing_dir_ok)

    def delete_root_dir_contents(self) -> None:
        with self._lock:
            self._written.clear()
            self._dirs.clear()
        self.fs.delete_dir_contents("/", accept_root_dir=True)

    def delete_file(self, path: str) -> None:
        self.forget(path)
        self.fs.delete_file(path)

    def move(self, src: str, dest: str) -> None:
        self.forget(src)
        self.forget(dest)
        self.fs.move(src, dest)

    def copy_file(self, src: str, dest: str) -> None:
        self.forget(dest)
        self.fs.copy_file(src, dest)

    # ---- what only reads: straight through -----------------------------------------------------------------
    def get_type_name(self) -> str:
        return f"only-changed-uploads+{self.fs.type_name}"

    def normalize_path(self, path: str) -> str:
        return self.fs.normalize_path(path)

    def get_file_info(self, paths: list[str]) -> list[pafs.FileInfo]:
        return self.fs.get_file_info(paths)

    def get_file_info_selector(self, selector: pafs.FileSelector) -> list[pafs.FileInfo]:
        return self.fs.get_file_info(selector)

    def open_input_stream(self, path: str) -> pa.NativeFile:
        return self.fs.open_input_stream(path)

    def open_input_file(self, path: str) -> pa.NativeFile:
        return self.fs.open_input_file(path)

    def equals(self, other) -> bool:
        return isinstance(other, OnlyChangedUploads) and self.fs.equals(other.fs)


class _HeldWrite:
    """A write through OnlyChangedUploads: held until close(), which writes it if it changed. A write
    dropped unclosed (a copy that failed half-way) writes nothing. Past HELD_BYTES it streams through."""

    def __init__(self, owner: OnlyChangedUploads, path: str, metadata):
        self.owner, self.path, self.metadata = owner, path, metadata
        self.held: io.BytesIO | None = io.BytesIO()
        self.stream: pa.NativeFile | None = None
        self.size = 0
        self.closed = False

    def write(self, data) -> int:
        self.size += len(data)
        if self.stream is not None:
            self.stream.write(data)
        else:
            self.held.write(data)
            # Too big to hold: write it as it comes and remember nothing. Not under the owner's _send lock (a
            # stream dropped unclosed would hold it for ever), so such a write may overlap one small write.
            if self.held.tell() > HELD_BYTES:
                self.owner.forget(self.path)
                self.stream = self.owner.fs.open_output_stream(self.path, metadata=self.metadata)
                self.stream.write(self.held.getbuffer())
                self.held = None
        return len(data)

    def tell(self) -> int:
        return self.size

    def flush(self) -> None:
        pass

    def writable(self) -> bool:
        return True

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.stream is not None:
            self.stream.close()
        else:
            self.owner.write_if_changed(self.path, self.held.getvalue(), self.metadata)
