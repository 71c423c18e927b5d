"""`asp-dist` command line: cells, theory, spec fields, and (when installed) sweeps and stats.

User mistakes end with one line on stderr, `asp-dist: error: ...`, and exit code 2; nothing
already written is touched.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from asp_dist.spec import FIELD_DOCS, FIELD_NAMES, CellSpec, SpecError, coerce_field

# Modules that add their own subcommands through register(subparsers).
PLUGINS = ("asp_dist.cli_sweep", "asp_dist.cli_stats")


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SpecError(f"--set expects KEY=VALUE, got {item!r}")
        out[key.strip()] = coerce_field(key.strip(), value.strip())
    return out


class StderrProgress:
    """A one-line progress display for a single cell, redrawn in place on a terminal."""

    def __init__(self, cell_id: str, stream=sys.stderr):
        self.cell_id, self.stream, self.start = cell_id, stream, time.monotonic()
        self.tty = stream.isatty()
        self.last_line = 0.0

    def __call__(self, phase: str, done: int, total: int, info: dict) -> None:
        now = time.monotonic()
        if not self.tty and done != total and now - self.last_line < 10:
            return  # in logs, a line every 10 s is enough
        self.last_line = now
        elapsed = now - self.start
        pct = 100.0 * done / max(total, 1)
        text = f"{self.cell_id} {phase} {done}/{total} ({pct:3.0f}%) {elapsed:6.1f}s"
        if self.tty:
            self.stream.write("\r" + text.ljust(78) + ("\n" if phase == "eval" else ""))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()


def cmd_cell(args: argparse.Namespace) -> int:
    import torch

    from asp_dist.training.cell import run_cell

    torch.set_num_threads(args.threads)
    spec = CellSpec(domain=args.domain, method=args.method, paired=args.paired, trial=args.trial,
                    **parse_overrides(args.set)).resolved()
    out = Path(args.out) if args.out else None
    if out is not None:
        if out.suffix != ".parquet":
            raise SpecError(f"--out must name a .parquet file, got {out}")
        if out.exists():
            raise SpecError(f"{out} already exists; finished results are never overwritten — choose another --out")
        if not out.parent.exists():
            raise SpecError(f"directory {out.parent} does not exist")
        if not os.access(out.parent, os.W_OK):
            raise SpecError(f"directory {out.parent} is not writable")
    progress = None if args.quiet else StderrProgress(spec.cell_id)
    row = run_cell(spec, progress=progress)
    if out is not None:
        write_single_row(row, out)
        print(f"wrote {out}", file=sys.stderr)
    print(json.dumps(row, indent=1, default=str, allow_nan=True))
    return 0


def write_single_row(row: dict[str, Any], out: Path) -> None:
    """One row to a new Parquet file with the sweep store's pinned schema, written atomically."""
    from asp_dist.fsutil import write_table_once
    from asp_dist.training.row import row_table

    if not write_table_once(row_table(row), out):
        raise SpecError(f"{out} already exists; finished results are never overwritten — choose another --out")


def cmd_theory(args: argparse.Namespace) -> int:
    from asp_dist.analysis import theory

    if args.probs and args.skew is not None:
        raise SpecError("give either --probs or --skew, not both")
    probs = None
    if args.probs:
        probs = [float(p) for p in args.probs.split(",")]
    elif args.skew is not None:
        probs = theory.skew_probs(args.actions, args.skew)
    try:
        result = theory.analyse(args.states, args.actions, probs)
    except ValueError as e:
        raise SpecError(str(e)) from None
    if args.json:
        print(json.dumps({**result.__dict__, "fraction_kept": result.fraction_kept}, indent=1))
        return 0
    print(f"S = {result.states} states, A = {result.actions} actions, distribution: {result.distribution}")
    print(f"  ln(all policies)  = S ln A                 = {result.log_all_policies:12.4f}")
    print(f"  ln(adversarially allowed) = ln multinomial = {result.log_adversarial_policies:12.4f}")
    print(f"  log-ratio, exact (lgamma)                  = {result.log_ratio_exact:12.4f}")
    print(f"  log-ratio, Stirling with ½ln(2πn) terms    = {result.log_ratio_stirling:12.4f}")
    if result.log_ratio_big_o is not None:
        print(f"  paper's big-O form ln S − A ln(S/A)        = {result.log_ratio_big_o:12.4f}")
    print(f"  fraction of policies kept                  = {result.fraction_kept:.4g}"
          f"  (1 in {math.exp(-result.log_ratio_exact):.4g})")
    return 0


def cmd_fields(args: argparse.Namespace) -> int:
    from asp_dist.domains import get_domain

    defaults = {}
    if args.domain:
        defaults = get_domain(args.domain).defaults
    for name in FIELD_NAMES:
        if args.domain and name.split("_")[0] in ("signaling", "particles", "vae", "levers") \
                and not name.startswith(args.domain + "_"):
            continue
        value = defaults.get(name, getattr(CellSpec(), name))
        print(f"{name:26s} {str(value):>10s}  {FIELD_DOCS[name]}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="asp-dist", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("cell", help="run one training cell and print its result row as JSON")
    p.add_argument("--domain", required=True)
    p.add_argument("--method", required=True, help="pc | osp | asp")
    p.add_argument("--paired", type=int, required=True, help="number of paired examples")
    p.add_argument("--trial", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any cell field (see `asp-dist fields`); repeatable")
    p.add_argument("--out", help="also write the row to this new .parquet file")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_cell)

    p = sub.add_parser("theory", help="policy-space pruning of the adversary (the paper's analysis)")
    p.add_argument("--states", "-S", type=int, required=True)
    p.add_argument("--actions", "-A", type=int, required=True)
    p.add_argument("--probs", help="comma-separated action distribution (default uniform)")
    p.add_argument("--skew", type=float, help="p_k ∝ exp(-skew·k), as in the signaling game")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_theory)

    p = sub.add_parser("fields", help="list every cell field with its default and meaning")
    p.add_argument("--domain", help="show this domain's defaults and knobs only")
    p.set_defaults(func=cmd_fields)

    for name in PLUGINS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name == name:
                continue
            raise
        module.register(sub)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (SpecError, FileNotFoundError, PermissionError) as e:
        print(f"asp-dist: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("asp-dist: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
