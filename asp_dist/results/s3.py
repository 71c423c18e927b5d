"""S3-compatible object storage for a sweep's results: a prefix in a bucket (``S3Path``), the clients that
reach it, and the one-line errors a user can fix. Where results live, local or S3, is
asp_dist.results.location (``as_path``, ``AnyPath``, and the writes and Parquet reads for either kind).
(About 560 lines, over the project's 500: ``S3Path`` is 235 of them and uses the clients, the retries and
the error wording below, which nothing else needs; split apart they would be two halves of one thing.)

``S3Path`` is a small, immutable, picklable object with the part of the ``pathlib`` API the store uses
(``/``, ``name``, ``stem``, ``parent``, ``relative_to``, ``exists``, ``is_file``, ``is_dir``,
``read_text``, ``rglob``, ``glob``, ``unlink`` ...), so the store's layout code reads the same as for a
local ``Path``, plus what object storage does differently:

- ``write_bytes`` is one whole-object PUT (atomic by the protocol: a reader sees the old object or
  the new one, never a part);
- ``create(data)`` is a *conditional* PUT (``If-None-Match: *``): it writes only if no object of
  that key exists and returns False otherwise. That is the object-storage form of the local
  ``os.link`` "never overwrites" write (documented by AWS S3 since 2024-08, MinIO and Cloudflare
  R2; moto's server honours it, tests/test_s3.py);
- there are no directories: ``mkdir`` does nothing and ``is_dir`` means "some object has this
  prefix".

Endpoint, region and credentials come from the standard AWS variables (``AWS_ENDPOINT_URL_S3`` or
``AWS_ENDPOINT_URL``, ``AWS_REGION`` or ``AWS_DEFAULT_REGION``, ``AWS_ACCESS_KEY_ID``,
``AWS_SECRET_ACCESS_KEY``, ``AWS_SESSION_TOKEN``, ``~/.aws``, an instance role), so MinIO, Ceph,
R2 and GCS's S3 API work unchanged. Reads, listings, deletes, Parquet datasets and Tune's storage
go through pyarrow's ``S3FileSystem`` (``filesystem``); only what pyarrow cannot do goes through boto3
(``client``): a PUT that is guaranteed to be one whole-object request, its conditional form
(``If-None-Match``), and a listing that also returns the server's clock (``server_listing``: the leases
of asp_dist.sweep.lease). Errors a user can fix (an endpoint that does not answer, refused credentials,
a missing bucket) become one-line ``StorageError``s (``storage_error``, ``check_bucket``).
"""

from __future__ import annotations

import fnmatch
import os
import re
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path, PurePosixPath
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Iterator
from urllib.parse import urlsplit

from asp_dist.errors import SpecError, StorageError

if TYPE_CHECKING:
    import pyarrow as pa
    import pyarrow.fs as pafs

S3_SCHEME = "s3://"
CONNECT_TIMEOUT_S = 5.0
REQUEST_TIMEOUT_S = 60.0
MAX_ATTEMPTS = 4  # the AWS SDKs' "standard" retry mode: transient errors and throttling are retried


# ---- configuration and clients ---------------------------------------------------------------------
@dataclass(frozen=True)
class S3Config:
    """The endpoint and region of the standard AWS variables (credentials stay with the SDKs' own chain)."""

    endpoint: str | None
    region: str

    @classmethod
    def from_env(cls) -> S3Config:
        endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL") or None
        region = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION") or "us-east-1"
        if endpoint is not None:
            parts = urlsplit(endpoint)
            if parts.scheme not in ("http", "https") or not parts.netloc:
                raise StorageError(f"AWS_ENDPOINT_URL={endpoint!r} is not an http(s) URL; write e.g. "
                                   f"http://127.0.0.1:9000")
        return cls(endpoint.rstrip("/") if endpoint else None, region)

    def describe(self) -> str:
        return self.endpoint or f"AWS S3 ({self.region})"


_LOCK = threading.Lock()
_CLIENTS: dict[tuple[int, S3Config], dict[str, Any]] = {}
_BUCKETS_CHECKED: set[tuple[S3Config, str]] = set()


def _clients(config: S3Config | None = None) -> dict[str, Any]:
    config = config or S3Config.from_env()
    key = (os.getpid(), config)
    with _LOCK:
        if key not in _CLIENTS:
            _CLIENTS[key] = {"config": config}
        return _CLIENTS[key]


def filesystem(config: S3Config | None = None, *, background_writes: bool = True) -> pafs.S3FileSystem:
    """pyarrow's S3 filesystem for the configured endpoint (one per process and kind). Credentials are left to
    the AWS SDK's chain, so pickling it (Tune sends it to every worker) carries no secret. Without
    `background_writes` a write is sent from the thread that closes it, not from Arrow's IO thread pool: what
    a filesystem written to from that pool's own threads needs (asp_dist.sweep.tune_storage)."""
    import pyarrow.fs as pafs

    held = _clients(config)
    key = "fs" if background_writes else "fs-foreground-writes"
    if key not in held:
        cfg: S3Config = held["config"]
        kwargs: dict[str, Any] = {}
        if cfg.endpoint:
            parts = urlsplit(cfg.endpoint)
            kwargs = {"endpoint_override": parts.netloc, "scheme": parts.scheme}
        # allow_delayed_open: a small object (Tune's state, a checkpoint under Arrow's part size) is sent as one
        # PutObject at close instead of a multipart upload.
        held[key] = pafs.S3FileSystem(region=cfg.region, connect_timeout=CONNECT_TIMEOUT_S, allow_delayed_open=True,
                                      request_timeout=REQUEST_TIMEOUT_S, background_writes=background_writes,
                                      retry_strategy=pafs.AwsStandardS3RetryStrategy(max_attempts=MAX_ATTEMPTS),
                                      **kwargs)
    return held[key]


def _probe_filesystem(config: S3Config, timeout_s: float) -> pafs.S3FileSystem:
    """An S3 filesystem whose requests give up after `timeout_s` without a retry (the first contact)."""
    import pyarrow.fs as pafs

    kwargs: dict[str, Any] = {}
    if config.endpoint:
        parts = urlsplit(config.endpoint)
        kwargs = {"endpoint_override": parts.netloc, "scheme": parts.scheme}
    return pafs.S3FileSystem(region=config.region, connect_timeout=min(CONNECT_TIMEOUT_S, timeout_s),
                             request_timeout=timeout_s, retry_strategy=pafs.AwsStandardS3RetryStrategy(max_attempts=1),
                             **kwargs)


def client(config: S3Config | None = None):
    """A boto3 S3 client for the configured endpoint (one per process): conditional PUTs and leases."""
    held = _clients(config)
    if "boto3" not in held:
        try:
            import boto3
            from botocore.config import Config
        except ImportError:
            raise StorageError("results on S3 need boto3 for conditional writes: pip install 'asp-dist[s3]'") \
                from None
        cfg: S3Config = held["config"]
        options: dict[str, Any] = dict(connect_timeout=CONNECT_TIMEOUT_S, read_timeout=REQUEST_TIMEOUT_S,
                                       retries={"max_attempts": MAX_ATTEMPTS, "mode": "standard"},
                                       s3={"addressing_style": "path" if cfg.endpoint else "auto"})
        try:  # botocore >= 1.36 adds CRC checksums that several S3-compatible stores refuse
            Config(request_checksum_calculation="when_required")
            options.update(request_checksum_calculation="when_required", response_checksum_validation="when_required")
        except TypeError:
            pass
        held["boto3"] = boto3.session.Session().client("s3", endpoint_url=cfg.endpoint, region_name=cfg.region,
                                                       config=Config(**options))
    return held["boto3"]


# ---- errors ------------------------------------------------------------------------------------------
_ACCESS_CODES = {"AccessDenied", "InvalidAccessKeyId", "SignatureDoesNotMatch", "ExpiredToken", "InvalidToken",
                 "TokenRefreshRequired", "403", "Forbidden", "ACCESS_DENIED", "INVALID_ACCESS_KEY_ID",
                 "SIGNATURE_DOES_NOT_MATCH", "EXPIRED_TOKEN", "INVALID_CLIENT_TOKEN_ID", "MISSING_AUTHENTICATION_TOKEN"}
_BUCKET_CODES = {"NoSuchBucket", "NO_SUCH_BUCKET"}
_NETWORK_CODES = {"NETWORK_CONNECTION", "REQUEST_TIMEOUT", "SLOW_DOWN", "SERVICE_UNAVAILABLE", "INTERNAL_FAILURE"}


def storage_error(err: BaseException, where: str, config: S3Config | None = None) -> StorageError:
    """One line that says what to fix, from a pyarrow OSError or a botocore exception."""
    config = config or S3Config.from_env()
    endpoint = config.describe()
    bucket = where[len(S3_SCHEME):].split("/", 1)[0] if where.startswith(S3_SCHEME) else where
    code, detail = "", " ".join(str(err).split()) or type(err).__name__
    name = type(err).__name__
    response = getattr(err, "response", None)
    if isinstance(response, dict):
        code = str(response.get("Error", {}).get("Code", ""))
        detail = response.get("Error", {}).get("Message") or detail
    elif isinstance(err, OSError):
        found = re.search(r"AWS Error ([A-Z_]+) during \w+ operation: ?(.*)", detail)
        if found:  # pyarrow: "When getting information for bucket 'b': AWS Error CODE during Op operation: text"
            code, detail = found.group(1), found.group(2).split(" (Request ID")[0].strip() or found.group(1)
    if name == "NoCredentialsError" or "No credentials" in detail or "MISSING_AUTHENTICATION_TOKEN" in code:
        return StorageError(f"no AWS credentials for {where}: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY "
                            f"(or a profile / instance role)")
    if code in _ACCESS_CODES:
        return StorageError(f"access to {where} refused by {endpoint} ({code}); check AWS_ACCESS_KEY_ID and "
                            f"AWS_SECRET_ACCESS_KEY (and AWS_SESSION_TOKEN)")
    if code in _BUCKET_CODES or (code in ("404", "NotFound") and name == "ClientError" and "/" not in where[5:]):
        return StorageError(f"bucket {bucket!r} does not exist at {endpoint}; create it first "
                            f"(asp-dist never creates buckets)")
    if name in ("EndpointConnectionError", "ConnectTimeoutError", "ReadTimeoutError", "ConnectionClosedError",
                "ProxyConnectionError", "SSLError") or code in _NETWORK_CODES:
        first = detail.split(";")[0]
        return StorageError(f"cannot reach the S3 endpoint {endpoint} for {where} ({first}); check "
                            f"AWS_ENDPOINT_URL and the network")
    return StorageError(f"S3 error on {where} at {endpoint}: {detail[:300]}")


def _is_not_found(err: BaseException) -> bool:
    response = getattr(err, "response", None)
    if isinstance(response, dict):
        return str(response.get("Error", {}).get("Code", "")) in ("404", "NoSuchKey", "NotFound")
    return isinstance(err, FileNotFoundError) or "Path does not exist" in str(err)


FIRST_ANSWER_ENV = "ASP_DIST_S3_TIMEOUT"  # the S3 twin of --connect-timeout (which sweep and resume apply too)
DEFAULT_FIRST_ANSWER_S = 20.0


_FIRST_ANSWER_S: list[float] = []  # set by first_answer_within (sweep and resume: --connect-timeout)


@contextmanager
def first_answer_within(seconds: float) -> Iterator[None]:
    """Within: the endpoint's first answer is awaited `seconds` (a command's flag, over the environment's)."""
    _FIRST_ANSWER_S.append(float(seconds))
    try:
        yield
    finally:
        _FIRST_ANSWER_S.pop()


def first_answer_timeout_s() -> float:
    """Seconds the endpoint has to answer the first request of a command (check_bucket): an endpoint that
    accepts connections and never answers would otherwise hold a command for the SDKs' retries (4 x 60 s)."""
    if _FIRST_ANSWER_S:
        return _FIRST_ANSWER_S[-1]
    try:
        value = float(os.environ.get(FIRST_ANSWER_ENV, DEFAULT_FIRST_ANSWER_S))
    except ValueError:
        raise StorageError(f"{FIRST_ANSWER_ENV}={os.environ[FIRST_ANSWER_ENV]!r} is not a number of seconds") from None
    if not value > 0 or value != value or value == float("inf"):
        raise StorageError(f"{FIRST_ANSWER_ENV} must be > 0 seconds and finite, got {value}")
    return value


def check_bucket(path: S3Path) -> None:
    """Refuse, in one line, an endpoint that does not answer (within first_answer_timeout_s), refused
    credentials or a missing bucket, before anything is read or written (once per process and bucket). An
    existing bucket is never created."""
    config = S3Config.from_env()
    if (config, path.bucket) in _BUCKETS_CHECKED:
        return
    import pyarrow.fs as pafs

    timeout_s = first_answer_timeout_s()

    def probe() -> None:
        # Its own filesystem, one attempt, each request bounded by the timeout: no request is left hanging
        # (pyarrow's S3 shutdown at exit would wait for it).
        fs = _probe_filesystem(config, timeout_s)
        info = fs.get_file_info(path.bucket)
        if info.type == pafs.FileType.NotFound:
            raise StorageError(f"bucket {path.bucket!r} does not exist at {config.describe()}; create it first "
                               f"(asp-dist never creates buckets)")
        # HeadBucket succeeds for some stores without the right to list; a listing is what every command needs.
        fs.get_file_info(pafs.FileSelector(f"{path.bucket}/{path.key}".rstrip("/"), allow_not_found=True,
                                           recursive=False))

    started = time.monotonic()
    answer: list[BaseException | None] = []

    def run() -> None:
        try:
            probe()
            answer.append(None)
        except BaseException as err:  # noqa: BLE001 - handed to the caller's thread
            answer.append(err)

    worker = threading.Thread(target=run, name="asp-s3-first-answer", daemon=True)
    worker.start()
    worker.join(2 * timeout_s + 5)  # a backstop: the probe's own timeouts end it first
    silent = f"no answer from the S3 endpoint {config.describe()} for {path} within {timeout_s:g} s; check " \
             f"AWS_ENDPOINT_URL, or raise --connect-timeout ({FIRST_ANSWER_ENV})"
    if not answer:
        raise StorageError(silent)
    if isinstance(answer[0], OSError):
        err = storage_error(answer[0], str(path), config)
        if "cannot reach" in str(err) and time.monotonic() - started >= timeout_s:
            raise StorageError(silent) from None  # it took the connection and said nothing
        raise err from None
    if answer[0] is not None:
        raise answer[0]
    _BUCKETS_CHECKED.add((config, path.bucket))


# ---- S3Path ------------------------------------------------------------------------------------------
_BUCKET_RE = re.compile(r"^[a-z0-9][a-z0-9.\-_]{1,254}$")


class S3Path:
    """An object key (or key prefix) in a bucket, with the pathlib API the store needs. Immutable,
    hashable and picklable (only bucket and key travel; clients are made per process)."""

    __slots__ = ("bucket", "key", "_info")

    def __init__(self, bucket: str, key: str = "", info: tuple[int, int] | None = None):
        self.bucket = bucket
        self.key = "/".join(p for p in key.split("/") if p and p != ".")
        self._info = info  # (size, mtime_ns) when known from a listing

    @classmethod
    def from_uri(cls, uri: str) -> S3Path:
        rest = uri[len(S3_SCHEME):]
        bucket, _, key = rest.partition("/")
        if not _BUCKET_RE.match(bucket) or ".." in key.split("/"):
            raise SpecError(f"{uri!r} is not an S3 location; write s3://BUCKET/PREFIX")
        return cls(bucket, key)

    def __getstate__(self):
        return (self.bucket, self.key)

    def __setstate__(self, state):
        self.bucket, self.key = state
        self._info = None

    # -- pure path operations
    def __str__(self) -> str:
        return f"{S3_SCHEME}{self.bucket}/{self.key}" if self.key else f"{S3_SCHEME}{self.bucket}"

    def __repr__(self) -> str:
        return f"S3Path({str(self)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, S3Path) and (self.bucket, self.key) == (other.bucket, other.key)

    def __hash__(self) -> int:
        return hash((S3Path, self.bucket, self.key))

    def __lt__(self, other: S3Path) -> bool:
        return (self.bucket, self.key) < (other.bucket, other.key)

    def __truediv__(self, part: str | os.PathLike) -> S3Path:
        return S3Path(self.bucket, f"{self.key}/{os.fspath(part)}")

    def joinpath(self, *parts: str) -> S3Path:
        out = self
        for part in parts:
            out = out / part
        return out

    @property
    def fs_path(self) -> str:
        """The path pyarrow's S3FileSystem takes (``bucket/key``)."""
        return f"{self.bucket}/{self.key}" if self.key else self.bucket

    @property
    def name(self) -> str:
        return self.key.rsplit("/", 1)[-1] if self.key else self.bucket

    @property
    def stem(self) -> str:
        return PurePosixPath(self.name).stem

    @property
    def suffix(self) -> str:
        return PurePosixPath(self.name).suffix

    @property
    def parent(self) -> S3Path:
        return S3Path(self.bucket, self.key.rsplit("/", 1)[0]) if "/" in self.key else S3Path(self.bucket)

    @property
    def parents(self) -> list[S3Path]:
        out, path = [], self
        while path.key:
            path = path.parent
            out.append(path)
        return out

    @property
    def parts(self) -> tuple[str, ...]:
        return (f"{S3_SCHEME}{self.bucket}", *(self.key.split("/") if self.key else ()))

    def relative_to(self, other: S3Path) -> PurePosixPath:
        if not isinstance(other, S3Path) or other.bucket != self.bucket or not (
                other.key == "" or self.key == other.key or self.key.startswith(other.key + "/")):
            raise ValueError(f"{self} is not in the subpath of {other}")
        return PurePosixPath(self.key[len(other.key):].lstrip("/") or ".")

    def expanduser(self) -> S3Path:
        return self

    def resolve(self) -> S3Path:
        return self

    absolute = resolve

    def mkdir(self, parents: bool = False, exist_ok: bool = False) -> None:
        """Object storage has no directories: a prefix exists once an object has it."""

    # -- queries
    def _fs_call(self, fn, *args):
        try:
            return fn(*args)
        except OSError as err:
            if _is_not_found(err):
                raise FileNotFoundError(f"{self} does not exist") from None
            raise storage_error(err, str(self)) from None

    def _file_info(self):
        return self._fs_call(filesystem().get_file_info, self.fs_path)

    def is_file(self) -> bool:
        import pyarrow.fs as pafs

        if self._info is not None:
            return True
        return bool(self.key) and self._file_info().type == pafs.FileType.File

    def is_dir(self) -> bool:
        """Some object lies under this prefix (one listing request)."""
        return next(self._list(recursive=True, limit=1), None) is not None

    def exists(self) -> bool:
        return self.is_file() or self.is_dir()

    def is_symlink(self) -> bool:
        return False

    def stat(self) -> SimpleNamespace:
        if self._info is None:
            info = self._file_info()
            import pyarrow.fs as pafs

            if info.type != pafs.FileType.File:
                raise FileNotFoundError(f"{self} does not exist")
            self._info = (info.size, info.mtime_ns or 0)
        size, mtime_ns = self._info
        return SimpleNamespace(st_ino=0, st_size=size, st_mtime_ns=mtime_ns, st_mtime=mtime_ns / 1e9)

    def _list(self, recursive: bool, limit: int | None = None) -> Iterator[S3Path]:
        """Objects under this prefix (files only), as S3Paths that know their size and mtime."""
        import pyarrow.fs as pafs

        selector = pafs.FileSelector(self.fs_path, recursive=recursive, allow_not_found=True)
        infos = self._fs_call(filesystem().get_file_info, selector)
        count = 0
        for info in infos:
            if info.type != pafs.FileType.File or info.path.endswith("/"):
                continue
            bucket, _, key = info.path.partition("/")
            yield S3Path(bucket, key, (info.size, info.mtime_ns or 0))
            count += 1
            if limit is not None and count >= limit:
                return

    def iterdir(self) -> Iterator[S3Path]:
        """The objects and sub-prefixes directly under this prefix."""
        import pyarrow.fs as pafs

        selector = pafs.FileSelector(self.fs_path, recursive=False, allow_not_found=True)
        for info in self._fs_call(filesystem().get_file_info, selector):
            bucket, _, key = info.path.rstrip("/").partition("/")
            yield S3Path(bucket, key, (info.size, info.mtime_ns or 0) if info.type == pafs.FileType.File else None)

    def rglob(self, pattern: str) -> list[S3Path]:
        return [p for p in self._list(recursive=True) if fnmatch.fnmatchcase(p.name, pattern)]

    def glob(self, pattern: str) -> list[S3Path]:
        return [p for p in self._list(recursive=False) if fnmatch.fnmatchcase(p.name, pattern)]

    # -- reading
    def read_bytes(self) -> bytes:
        def read() -> bytes:
            with filesystem().open_input_stream(self.fs_path) as fh:
                return fh.read()

        return self._fs_call(read)

    def read_text(self, encoding: str = "utf-8") -> str:
        return self.read_bytes().decode(encoding)

    def open_input(self) -> pa.NativeFile:
        """A random-access file (Parquet footers are read with range requests)."""
        return self._fs_call(filesystem().open_input_file, self.fs_path)

    # -- writing
    def _put(self, data: bytes, only_new: bool) -> bool:
        """One whole-object PutObject (boto3: pyarrow's output stream may split an object into a multipart
        upload and cannot send If-None-Match). With `only_new`, False if an object of this key exists."""
        s3 = client()
        condition = {"IfNoneMatch": "*"} if only_new else {}
        for attempt in range(MAX_ATTEMPTS):
            try:
                s3.put_object(Bucket=self.bucket, Key=self.key, Body=data, **condition)
                return True
            except Exception as err:  # noqa: BLE001 - botocore's exceptions are made at run time
                code = str(getattr(err, "response", {}).get("Error", {}).get("Code", ""))
                if only_new and code in ("PreconditionFailed", "412"):
                    return False
                if code in ("ConditionalRequestConflict", "409") and attempt + 1 < MAX_ATTEMPTS:
                    continue  # a concurrent conditional write of the same key is in flight: ask again
                raise storage_error(err, str(self)) from None
        return False

    def write_bytes(self, data: bytes) -> int:
        """One whole-object PUT: readers see the old object or the new one, never a part."""
        self._put(data, only_new=False)
        return len(data)

    def write_text(self, text: str, encoding: str = "utf-8") -> int:
        return self.write_bytes(text.encode(encoding))

    def create(self, data: bytes) -> bool:
        """A conditional PUT (``If-None-Match: *``): True if this call created the object, False if an
        object of this key already existed (it is left as it was)."""
        return self._put(data, only_new=True)

    def unlink(self, missing_ok: bool = False) -> None:
        """DeleteObject (boto3: pyarrow's delete leaves a ``dir/`` marker object behind to keep the parent)."""
        if not missing_ok and not self.is_file():
            raise FileNotFoundError(f"{self} does not exist")
        try:
            client().delete_object(Bucket=self.bucket, Key=self.key)
        except Exception as err:  # noqa: BLE001 - botocore's exceptions
            if not _is_not_found(err):
                raise storage_error(err, str(self)) from None

    def delete_tree(self) -> None:
        """Delete every object under this prefix (best effort: a missing prefix is fine)."""
        for path in self._list(recursive=True):
            path.unlink(missing_ok=True)


# ---- uploads and listings ------------------------------------------------------------------------------
def upload_tree(local_dir: Path, target: S3Path) -> list[S3Path]:
    """Copy every file under `local_dir` to the same relative keys under `target` (one PUT each)."""
    written = []
    for path in sorted(p for p in Path(local_dir).rglob("*") if p.is_file()):
        dest = target.joinpath(*path.relative_to(local_dir).parts)
        dest.write_bytes(path.read_bytes())
        written.append(dest)
    return written


def server_listing(prefix: S3Path) -> tuple[list[dict[str, Any]], datetime]:
    """The objects under `prefix` (Key, LastModified, Size) and the server's clock at that moment (the
    HTTP Date of the same answer), so that ages are measured on one clock whatever the nodes' clocks say."""
    from email.utils import parsedate_to_datetime

    s3 = client()
    objects: list[dict[str, Any]] = []
    token = None
    server_now = None
    try:
        while True:
            kwargs = dict(Bucket=prefix.bucket, Prefix=prefix.key.rstrip("/") + "/")
            if token:
                kwargs["ContinuationToken"] = token
            answer = s3.list_objects_v2(**kwargs)
            date = answer.get("ResponseMetadata", {}).get("HTTPHeaders", {}).get("date")
            if date and server_now is None:
                server_now = parsedate_to_datetime(date)
            objects += [o for o in answer.get("Contents", []) if not o["Key"].endswith("/")]
            token = answer.get("NextContinuationToken")
            if not token:
                break
    except Exception as err:  # noqa: BLE001 - botocore's exceptions
        raise storage_error(err, str(prefix)) from None
    if server_now is None:
        from datetime import timezone

        server_now = datetime.now(timezone.utc)
    return objects, server_now
