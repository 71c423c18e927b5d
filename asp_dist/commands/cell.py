"""`asp-dist cell`: one training cell here, its result row as JSON (and optionally a new .parquet file)."""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path
from typing import Any

from asp_dist.commands.common import check_data, int_between, non_empty, parse_overrides, refuse_set
from asp_dist.errors import SpecError
from asp_dist.spec import CellSpec


class CellProgressPrinter:
    """Prints one cell's ProgressFn calls on stderr: one line redrawn in place on a terminal, a line
    every 10 s in a log."""

    def __init__(self, cell_id: str, stream=sys.stderr):
        self.cell_id, self.stream, self.start = cell_id, stream, time.monotonic()
        self.tty = stream.isatty()
        self.last_line = 0.0

    def __call__(self, phase: str, done: int, total: int, info: dict) -> None:
        now = time.monotonic()
        if not self.tty and done != total and now - self.last_line < 10:
            return
        self.last_line = now
        pct = 100.0 * done / max(total, 1)
        text = f"{self.cell_id} {phase} {done}/{total} ({pct:3.0f}%) {now - self.start:6.1f}s"
        if self.tty:
            self.stream.write("\r" + text.ljust(78) + ("\n" if phase == "eval" else ""))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()


CELL_FLAGS = ("domain", "method", "paired", "trial")  # the fields `asp-dist cell` takes as its own flags


def cmd_cell(args: argparse.Namespace) -> int:
    refuse_set(args.set, {k: f"{k} is a flag of `asp-dist cell`; give it as --{k} instead" for k in CELL_FLAGS})
    overrides = parse_overrides(args.set)
    spec = CellSpec(domain=args.domain, method=args.method, paired=args.paired, trial=args.trial,
                    **overrides).resolved()
    out = Path(args.out) if args.out is not None else None
    if out is not None:
        from asp_dist.results.query import check_output_file

        if out.suffix != ".parquet":
            raise SpecError(f"--out must name a .parquet file, got {out}")
        if out.exists() or out.is_symlink():
            raise SpecError(f"{out} already exists; finished results are never overwritten — choose another --out")
        check_output_file(out)
    check_data([spec])
    import torch

    from asp_dist.training.bases import BaseRejected
    from asp_dist.training.cell import run_cell
    from asp_dist.training.pipeline import CellDiverged
    from asp_dist.training.row import InvalidRow

    torch.set_num_threads(args.threads)
    try:
        row = run_cell(spec, progress=None if args.quiet else CellProgressPrinter(spec.cell_id))
    except (BaseRejected, CellDiverged, InvalidRow) as e:  # the cell ran and failed: no row, exit 1 as a sweep's
        print(f"asp-dist: error: cell {spec.cell_id} failed: {type(e).__name__}: {' '.join(str(e).split())}",
              file=sys.stderr)
        return 1
    except (MemoryError, RuntimeError) as e:  # within CellSpec's size estimates, yet too big for this machine
        asked = re.search(r"allocate (\d+) bytes", str(e))
        if not isinstance(e, MemoryError) and asked is None:
            raise
        raise SpecError(f"out of memory for this cell {spec.cell_id}"
                        + (f": it asked for {int(asked[1])} bytes at once" if asked else "")
                        + "; lower its sizes (see `asp-dist fields`)") from None
    if out is not None:
        write_single_row(row, out)
        print(f"wrote {out}", file=sys.stderr)
    print(json.dumps(row, indent=1, default=str, allow_nan=True))
    return 0


def write_single_row(row: dict[str, Any], out: Path) -> None:
    """One row to a new Parquet file with the store's pinned schema, written atomically."""
    from asp_dist.fsutil import link_table_once
    from asp_dist.training.row import row_table

    if not link_table_once(row_table(row), out):
        raise SpecError(f"{out} already exists; finished results are never overwritten — choose another --out")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("cell", help="run one training cell and print its result row as JSON")
    p.add_argument("--domain", required=True)
    p.add_argument("--method", required=True, help="pc | osp | asp (or a plugin's), or an arm of one: osp@default")
    p.add_argument("--paired", type=int, required=True, help="number of paired examples")
    p.add_argument("--trial", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any cell field (see `asp-dist fields`); repeatable")
    p.add_argument("--out", type=non_empty, help="also write the row to this new .parquet file")
    # torch.set_num_threads fails past 2^31, and threads beyond the cores only slow a cell down
    p.add_argument("--threads", type=int_between(1, 1024), default=1, help="torch threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_cell)
