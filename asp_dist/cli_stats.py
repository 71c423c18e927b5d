"""`asp-dist stats` and `asp-dist query`: argument parsing and the stats job's orchestration.

`asp_dist.cli` calls `register(subparsers)`; every subcommand sets `func(args) -> exit code`.
User errors raise SpecError (cli.py prints the one-line message and exits 2). Run standalone
with `python -m asp_dist.cli_stats stats results/<sweep>` while cli.py is not there.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path
from typing import Sequence

from asp_dist.spec import SpecError


def parse_ranges(items: Sequence[str]) -> dict[str, tuple[int, int] | None]:
    from asp_dist.analysis.stats import PAPER_PAIRED_RANGES

    ranges: dict[str, tuple[int, int] | None] = dict(PAPER_PAIRED_RANGES)
    for item in items or ():
        domain, sep, value = item.partition("=")
        try:
            if not sep or not domain:
                raise ValueError
            if value == "all":
                ranges[domain] = None
                continue
            lo, _, hi = value.partition("-")
            lo_i, hi_i = int(lo), int(hi or lo)
            if lo_i > hi_i or lo_i < 0:
                raise ValueError
        except ValueError:
            raise SpecError(f"--paired-range {item!r}: write DOMAIN=LO-HI (e.g. particles=2-4) or DOMAIN=all") from None
        ranges[domain] = (lo_i, hi_i)
    return ranges


def parse_thresholds(items: Sequence[str]) -> dict[str, float]:
    out = {}
    for item in items or ():
        domain, sep, value = item.partition("=")
        try:
            if not sep or not domain:
                raise ValueError
            out[domain] = float(value)
        except ValueError:
            raise SpecError(f"--threshold {item!r}: write DOMAIN=VALUE (e.g. signaling=0.75)") from None
    return out


def output_dir(inputs: Sequence[str], out: str | None) -> Path:
    if out:
        return Path(out)
    if len(inputs) == 1:
        from asp_dist.results.query import locate_sweep

        candidate = locate_sweep(inputs[0])  # a directory or a bare sweep name
        if candidate.is_dir():
            return candidate
    raise SpecError("several inputs or single files: say where to write the stats with --out DIR")


def run_job(inputs: Sequence[str], out: str | None = None, cfg=None, figures: bool = True, command: str = "",
            log=print) -> Path:
    """The whole job: read rows, compute tables, write stats/, figures/ and report.md. Returns report.md."""
    from asp_dist.analysis.plots import plot_all
    from asp_dist.analysis.report import write_report
    from asp_dist.analysis.stats import run_stats, write_tables
    from asp_dist.results.query import cell_files

    cell_files(inputs)  # a missing or empty input is the first thing to report
    out_dir = output_dir(inputs, out)
    start = time.perf_counter()
    result = run_stats(inputs, cfg)
    log(f"read and analysed {len(result.rows)} rows from {len(result.inputs.files)} files "
        f"({', '.join(sorted(result.layouts))}) in {time.perf_counter() - start:.1f} s")
    written = write_tables(result, out_dir)
    log(f"wrote {len(written)} tables to {out_dir / 'stats'}")
    figs, notes = plot_all(result, out_dir / "figures") if figures else ([], [])
    if figures:
        log(f"wrote {len(figs)} figures (PNG + SVG) to {out_dir / 'figures'}")
    report = write_report(result, out_dir, figs, notes, sources=list(inputs), command=command)
    for note in result.notes + notes:
        log(f"note: {note}")
    log(f"report: {report} ({time.perf_counter() - start:.1f} s in all)")
    return report


def cmd_stats(args: argparse.Namespace) -> int:
    from asp_dist.analysis.stats import StatsConfig

    if args.bootstrap < 100:
        raise SpecError("--bootstrap must be at least 100 resamples")
    if not 0 < args.alpha < 1:
        raise SpecError("--alpha must be between 0 and 1")
    cfg = StatsConfig(metric=args.metric, paired_ranges=parse_ranges(args.paired_range),
                      thresholds=parse_thresholds(args.threshold), alpha=args.alpha, n_boot=args.bootstrap,
                      seed=args.seed)
    command = "asp-dist stats " + " ".join(shlex.quote(a) for a in getattr(args, "argv", []) or args.sweeps)
    run_job(args.sweeps, args.out, cfg, figures=not args.no_figures, command=command,
            log=(lambda *a: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr)))
    return 0


def cmd_query(args: argparse.Namespace) -> int:
    from asp_dist.results.query import run_query, write_result

    columns = [c.strip() for c in args.columns.split(",") if c.strip()] if args.columns else None
    df = run_query(args.sweeps, where=args.where, columns=columns, sql=args.sql, limit=args.limit)
    write_result(df, args.format, args.out)
    if args.out:
        print(f"{len(df)} rows -> {args.out}", file=sys.stderr)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("stats", help="statistics, figures and report.md of one or more sweeps",
                              description="Turn a sweep's rows into tables (stats/), figures (figures/) and report.md.")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP",
                   help="sweep directory results/<sweep> (or any directory / .parquet files); several are merged")
    p.add_argument("--out", help="directory for stats/, figures/ and report.md (default: the single sweep directory)")
    p.add_argument("--metric", default="eval_mixed", help="metric column to analyse (default: eval_mixed)")
    p.add_argument("--paired-range", action="append", default=[], metavar="DOMAIN=LO-HI",
                   help="paired counts of the Friedman test (defaults: particles=2-4 levers=4-8 vae=8-32, others all)")
    p.add_argument("--threshold", action="append", default=[], metavar="DOMAIN=VALUE",
                   help="data-efficiency threshold of the metric (defaults: vae=0.06, levers=0.317, else 90%% of base)")
    p.add_argument("--alpha", type=float, default=0.05, help="significance level (default 0.05)")
    p.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples (default 2000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--no-figures", action="store_true", help="tables and report only")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_stats)

    q = subparsers.add_parser("query", help="filter a sweep's rows or run SQL on them",
                              description="Rows of one or more sweeps. --where takes a SQL boolean expression "
                                          "(DuckDB), --sql a whole query over the view `cells`.")
    q.add_argument("sweeps", nargs="+", metavar="SWEEP", help="sweep directory, directory or .parquet files")
    q.add_argument("--where", help="SQL condition, e.g. \"method = 'asp' AND paired >= 2\"")
    q.add_argument("--columns", help="comma-separated columns to show (default: all)")
    q.add_argument("--sql", help="a full SQL query over the view `cells`, e.g. \"SELECT method, median(eval_mixed) "
                                 "FROM cells GROUP BY method\"")
    q.add_argument("--format", default="table", choices=("table", "csv", "json", "parquet"),
                   help="output format (json = one object per line; parquet needs --out)")
    q.add_argument("--out", help="write to this file instead of stdout")
    q.add_argument("--limit", type=int, help="at most this many rows (with --where/--columns)")
    q.set_defaults(func=cmd_query)


def main(argv: Sequence[str] | None = None) -> int:
    """Standalone entry point mirroring cli.py's handling (SpecError -> message, exit 2)."""
    parser = argparse.ArgumentParser(prog="asp-dist")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    args.argv = list(argv if argv is not None else sys.argv[1:])[1:]
    try:
        return args.func(args)
    except SpecError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
