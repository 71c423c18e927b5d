"""Bad input to `asp-dist sweep | resume | status`: one clear line, exit 2, nothing already written
touched — all refused before Ray starts. Also the status command and the sweep's counter line."""

from __future__ import annotations

import io

import pytest
from harness import finished_row

from asp_dist.cli import main
from asp_dist.results import store
from asp_dist.sweep.ledger import new_manifest, sweep_lock, sweep_status
from asp_dist.sweep.progress import SweepCounter, format_duration
from asp_dist.sweep.spaces import expand


def run_cli(capsys, *argv):
    try:
        code = main(list(argv))
    except SystemExit as e:  # argparse's own errors, the bounds of a flag's type among them
        code = e.code
    err = capsys.readouterr().err
    return code, err


def one_line_error(code, err, needle):
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("asp-dist: error: "), err
    assert needle in lines[0], lines[0]


def snapshot(root):
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


@pytest.fixture
def started_sweep(tmp_path):
    """A sweep 'exp' over smoke with its manifest and one finished cell, as a crash would leave it."""
    specs = expand("smoke")
    sweep_dir = tmp_path / "results" / "exp"
    sweep_dir.mkdir(parents=True)
    store.write_manifest(sweep_dir, new_manifest("exp", "smoke", specs))
    row = finished_row(specs[0])
    store.write_row(sweep_dir, row, sweep_id="exp")
    store.record_failure(sweep_dir, specs[1].cell_id, "signaling", specs[1].method, "Boom: it broke")
    return sweep_dir


def test_unknown_space(capsys, tmp_path):
    code, err = run_cli(capsys, "sweep", "no-such-space", "--results", str(tmp_path))
    one_line_error(code, err, "unknown space 'no-such-space'")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("text, needle", [
    ("[[grid]]\naxes = { domain = ['chess'] }", "unknown domain 'chess'"),
    ("[[grid]]\naxes = { method = ['xsp'] }", "unknown method 'xsp'"),
    ("[[grid]]\naxes = { paired = [-3] }", "paired must be an integer >= 0"),
    ("[[grid]]\naxes = { train_steps = [0] }", "train_steps must be >= 1"),
    ("[[grid]]\naxes = { signaling_tokens = [1] }", "signaling_tokens must be >= 2"),
])
def test_bad_domain_method_or_value(capsys, tmp_path, text, needle):
    space = tmp_path / "bad.toml"
    space.write_text(text)
    code, err = run_cli(capsys, "sweep", str(space), "--results", str(tmp_path / "results"))
    one_line_error(code, err, needle)
    assert not (tmp_path / "results").exists()


def test_bad_numbers_and_names(capsys, tmp_path):
    one_line_error(*run_cli(capsys, "sweep", "smoke", "--workers", "0", "--results", str(tmp_path)),
                   "--workers must be >= 1")
    one_line_error(*run_cli(capsys, "sweep", "smoke", "--checkpoint-every", "0", "--results", str(tmp_path)),
                   "--checkpoint-every must be > 0")
    with pytest.raises(SystemExit) as exit_info:  # argparse's own errors: the same one line
        main(["sweep", "smoke", "--workers", "two"])
    one_line_error(exit_info.value.code, capsys.readouterr().err, "argument --workers: invalid int value: 'two'")
    one_line_error(*run_cli(capsys, "sweep", "smoke", "--name", "../escape", "--results", str(tmp_path)),
                   "invalid sweep name")
    assert not any(tmp_path.iterdir())


def test_unwritable_results_dir(capsys, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    code, err = run_cli(capsys, "sweep", "smoke", "--results", str(blocker / "results"))
    one_line_error(code, err, "is not writable")
    assert blocker.read_text() == "not a directory"


def test_existing_dir_that_is_not_a_sweep(capsys, tmp_path):
    (tmp_path / "smoke").mkdir()
    (tmp_path / "smoke" / "precious.txt").write_text("mine")
    code, err = run_cli(capsys, "sweep", "smoke", "--results", str(tmp_path))
    one_line_error(code, err, "is not a sweep")
    assert snapshot(tmp_path)["smoke/precious.txt"] == b"mine"


def test_other_grid_on_same_name_is_refused(capsys, started_sweep):
    before = snapshot(started_sweep)
    space = started_sweep.parent.parent / "other.toml"
    space.write_text("[[grid]]\naxes = { method = ['asp'], paired = [1, 2] }")
    code, err = run_cli(capsys, "sweep", str(space), "--name", "exp", "--results", str(started_sweep.parent))
    one_line_error(code, err, "was started with another grid")
    after = snapshot(started_sweep)
    assert {k: v for k, v in after.items() if k != ".lock"} == {k: v for k, v in before.items() if k != ".lock"}


def test_second_concurrent_sweep_is_refused_by_the_lock(capsys, started_sweep):
    before = snapshot(started_sweep)
    with sweep_lock(started_sweep):
        code, err = run_cli(capsys, "sweep", "smoke", "--name", "exp", "--results", str(started_sweep.parent))
        one_line_error(code, err, "is already running (pid")
        code, err = run_cli(capsys, "resume", "exp", "--results", str(started_sweep.parent))
        one_line_error(code, err, "is already running")
        status = sweep_status("exp", started_sweep.parent)
        assert "RUNNING (pid" in status
    assert {k: v for k, v in snapshot(started_sweep).items() if k != ".lock"} == \
        {k: v for k, v in before.items() if k != ".lock"}
    assert "not running" in sweep_status("exp", started_sweep.parent)


def test_resume_and_status_of_unknown_sweep(capsys, tmp_path):
    one_line_error(*run_cli(capsys, "resume", "ghost", "--results", str(tmp_path)), "no sweep 'ghost'")
    one_line_error(*run_cli(capsys, "status", "ghost", "--results", str(tmp_path)), "no sweep 'ghost'")


def test_status_counts_per_domain_and_method(capsys, started_sweep):
    code = main(["status", "exp", "--results", str(started_sweep.parent)])
    out = capsys.readouterr().out
    assert code == 0
    lines = out.splitlines()
    assert "18 cells" in lines[0] and "not running" in lines[0]
    table = {tuple(line.split()[:2]): [int(x) for x in line.split()[2:]] for line in lines[2:5]}
    assert sum(v[0] for v in table.values()) == 1 and sum(v[1] for v in table.values()) == 1
    assert sum(sum(v) for v in table.values()) == 18
    assert lines[5].split() == ["total", "1", "1", "16"]
    assert "Boom: it broke" in out


def test_counter_line_counts_and_eta():
    out = io.StringIO()
    cells = {f"c{i}": "signaling/asp" for i in range(10)}
    p = SweepCounter("s", cells, done={"c0", "c1", "c2", "c3"}, stream=out, log_interval_s=0.0)
    assert "done 4/10" in p.line() and "pending 6" in p.line() and "ETA ?" in p.line()
    p.start -= 10.0
    p.update(done={f"c{i}" for i in range(6)}, running={"c6", "c7"}, failed={"c8"})
    line = out.getvalue().splitlines()[-1]
    assert "done 6/10  running 2  failed 1  pending 1" in line
    assert "12.0 cells/min  ETA 0:15" in line  # 2 cells in 10 s, 3 left
    p.update(running={"c7"})  # the running count alone never prints a line in a log
    assert len(out.getvalue().splitlines()) == 1
    p.finish()
    assert format_duration(3725) == "1:02:05" and format_duration(None) == "?"
