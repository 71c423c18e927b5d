"""The sweep's progress view: change-only lines in a log, a live block within 80 columns on a terminal."""

from __future__ import annotations

import io

from rich.console import Console

from asp_dist.sweep.progress import WIDTH, SweepCounter

CELLS = {**{f"p{i}": "particles/asp" for i in range(40)}, **{f"v{i}": "vae/osp" for i in range(20)}}


def test_a_log_gets_a_line_per_change_at_most_every_interval():
    out = io.StringIO()
    p = SweepCounter("calib", CELLS, stream=out, log_interval_s=3600.0)
    for i in range(30):  # thirty finished cells and running flicker within one interval
        p.update(done={f"p{j}" for j in range(i)}, running={f"p{i}"})
        p.update(running=set())
    assert len(out.getvalue().splitlines()) == 1, "one line in the first interval, none for flicker"
    p.finish()
    last = out.getvalue().splitlines()[-1]
    assert "done 29/60" in last and "failed 0" in last and len(out.getvalue().splitlines()) == 2


def test_the_live_view_fits_80_columns_and_says_everything():
    p = SweepCounter("a-rather-long-calibration-sweep-name", CELLS, done={"p0"}, where="/data/" + "x" * 120)
    p.start -= 60
    p.update(done={"p0", "p1", "p2", "v0"}, running={"p3", "v1"}, failed={"v2"},
             last_failure="vae-osp-p8-t3-0123456789: MNISTError: " + "the file is not an IDX file " * 5)
    console = Console(width=WIDTH, record=True, force_terminal=True, file=io.StringIO())
    console.print(p.render())
    lines = console.export_text().splitlines()
    assert max(len(line) for line in lines) <= WIDTH
    text = "\n".join(lines)
    assert "4/60 done, 2 running, 1 failed, 53 pending" in text
    assert "cells/min" in text and "ETA" in text
    rows = {line.split()[0]: line.split()[1:] for line in lines if line.startswith(("particles/", "vae/"))}
    assert rows == {"particles/asp": ["3", "1", "0", "36"], "vae/osp": ["1", "1", "1", "17"]}
    assert "last failure: vae-osp-p8-t3-0123456789: MNISTError" in text and "rows → /data/" in text


def test_a_terminal_gets_the_live_view():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    out = Tty()
    p = SweepCounter("s", CELLS, stream=out)
    p.update(done={"p0"})
    p.finish()
    assert "1/60 done" in out.getvalue() and "[s] done" not in out.getvalue()


def test_bases_trained_first_are_counted_until_the_last_one():
    """A packed sweep's bases come first (packing.bases_first): while they train no cell moves, so the view
    counts them, in the log and on a terminal, until the last is trained."""
    out = io.StringIO()
    p = SweepCounter("words", CELLS, stream=out, log_interval_s=0.0, bases=2)
    p.draw(force=True)
    p.base_finished()
    p.base_finished()
    p.update(done={"p0"})
    lines = out.getvalue().splitlines()
    assert [line.split("]")[1].split("done")[0].strip() for line in lines] == ["bases 0/2", "bases 1/2", "", ""]
    console = Console(width=WIDTH, record=True, force_terminal=True, file=io.StringIO())
    console.print(SweepCounter("words", CELLS, bases=3).render())
    assert "words: bases 0/3, 0/60 done" in console.export_text()
