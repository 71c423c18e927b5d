"""asp_dist.sweep.tune_storage on a real local filesystem: unchanged files are not written again, anything
else is, and nothing remembered outlives a delete or a pickle. (On S3, with Tune's own copy, and through a
whole sweep: tests/test_s3.py.)"""

import gc
import os
import pickle

import pyarrow.fs as pafs
import pytest

from asp_dist.sweep import tune_storage
from asp_dist.sweep.tune_storage import only_changed_uploads


@pytest.fixture
def tree(tmp_path):
    src = tmp_path / "src"
    (src / "trial-a").mkdir(parents=True)
    (src / "trial-a" / "params.json").write_text('{"x": 1}')
    (src / "experiment_state.json").write_text("state 1")
    return src, tmp_path / "dst"


def stamps(root):
    return {p.relative_to(root).as_posix(): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


def age(root):
    """Set every file's mtime to the epoch, so that a rewrite shows even within the clock's tick."""
    for p in root.rglob("*"):
        if p.is_file():
            os.utime(p, ns=(0, 0))


def copy(src, dst, fs):
    pafs.copy_files(str(src), str(dst), destination_filesystem=fs)  # threaded, as Tune's sync to a PyFileSystem


def test_a_second_copy_writes_only_the_changed_file(tree):
    src, dst = tree
    fs = only_changed_uploads(pafs.LocalFileSystem())
    copy(src, dst, fs)
    assert (dst / "trial-a" / "params.json").read_text() == '{"x": 1}' and len(stamps(dst)) == 2
    age(dst)
    (src / "experiment_state.json").write_text("state 2")
    (src / "trial-b").mkdir()
    (src / "trial-b" / "params.json").write_text("{}")
    copy(src, dst, fs)
    second = stamps(dst)
    assert second["trial-a/params.json"] == 0, "an unchanged file was written again"
    assert second["experiment_state.json"] != 0
    assert (dst / "experiment_state.json").read_text() == "state 2" and (dst / "trial-b" / "params.json").exists()


def test_a_deleted_directory_is_written_again_and_a_write_never_closed_writes_nothing(tree):
    src, dst = tree
    fs = only_changed_uploads(pafs.LocalFileSystem())
    copy(src, dst, fs)
    fs.delete_dir(str(dst / "trial-a"))
    copy(src, dst, fs)
    assert (dst / "trial-a" / "params.json").read_text() == '{"x": 1}'
    fs.delete_file(str(dst / "experiment_state.json"))
    copy(src, dst, fs)
    assert (dst / "experiment_state.json").read_text() == "state 1"

    dropped = fs.open_output_stream(str(dst / "half.bin"))
    dropped.write(b"half a checkpoint")
    del dropped  # a copy that failed half-way never closes its stream
    gc.collect()
    assert not (dst / "half.bin").exists()


def test_a_pickled_copy_remembers_nothing_and_a_large_write_streams_through(tree, monkeypatch):
    src, dst = tree
    fs = only_changed_uploads(pafs.LocalFileSystem())
    copy(src, dst, fs)
    worker = pickle.loads(pickle.dumps(fs))  # what a Tune worker gets
    age(dst)
    copy(src, dst, worker)
    assert stamps(dst)["trial-a/params.json"] != 0, "a worker trusted the driver's memory"

    monkeypatch.setattr(tune_storage, "HELD_BYTES", 1000)
    big = bytes(range(256)) * 20
    for _ in range(2):  # too big to hold: written both times, whole
        with fs.open_output_stream(str(dst / "state.pt")) as out:
            for i in range(0, len(big), 700):
                out.write(big[i:i + 700])
        assert (dst / "state.pt").read_bytes() == big
    with fs.open_input_stream(str(dst / "state.pt")) as f:
        assert f.read() == big
