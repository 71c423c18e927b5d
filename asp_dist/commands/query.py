"""`asp-dist query`: filters or DuckDB SQL over a sweep's rows or learning curves (no torch, no Ray)."""

from __future__ import annotations

import argparse
import sys

from asp_dist.commands.common import add_results, int_between, non_empty, non_empty_argument
from asp_dist.errors import SpecError


def cmd_query(args: argparse.Namespace) -> int:
    from asp_dist.results.query import check_output_file, run_query, where_expression, write_result

    columns = [c.strip() for c in args.columns.split(",") if c.strip()] if args.columns is not None else None
    if args.columns is not None and not columns:
        raise SpecError("--columns is empty; name the columns to show (comma-separated) or leave it out")
    if args.sql is not None and (args.where is not None or columns or args.limit is not None):
        raise SpecError("--sql is a whole query; put the filter, the columns and any LIMIT inside it "
                        "instead of --where/--columns/--limit")
    if args.where is not None:
        where_expression(args.where)
    if args.format == "parquet" and args.out is None:
        raise SpecError("--format parquet needs --out FILE")
    if args.force and args.out is None:
        raise SpecError("--force only applies to --out FILE")
    if args.out is not None:
        check_output_file(args.out, args.force)
    df = run_query(args.sweeps, where=args.where, columns=columns, sql=args.sql, limit=args.limit,
                   results=args.results, curves=args.curves)
    write_result(df, args.format, args.out, force=args.force)
    if args.out:
        print(f"{len(df)} rows -> {args.out}", file=sys.stderr)
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("query", help="filter a sweep's rows or run SQL on them",
                       description="Rows of one or more sweeps. --where takes a SQL boolean expression "
                                   "(DuckDB), --sql a whole query over the view `cells`.")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP", type=non_empty_argument,
                   help="sweep name (under --results) or directory, any directory or .parquet files")
    add_results(p)
    p.add_argument("--where", help="SQL condition, e.g. \"method = 'asp' AND paired >= 2\"")
    p.add_argument("--columns", help="comma-separated columns to show (default: all)")
    p.add_argument("--sql", help="a full SQL query over the view `cells`, e.g. \"SELECT method, median(eval_mixed) "
                                 "FROM cells GROUP BY method\"")
    p.add_argument("--format", default="table", choices=("table", "csv", "json", "parquet"),
                   help="output format (json = one object per line; parquet needs --out)")
    p.add_argument("--out", type=non_empty,
                   help="write to this new file instead of stdout (never inside a sweep's directory)")
    p.add_argument("--force", action="store_true", help="let --out overwrite an existing file")
    p.add_argument("--limit", type=int_between(0, 2**63 - 1, "DuckDB's LIMIT is a 64-bit integer"),
                   help="at most this many rows (with --where/--columns)")
    p.add_argument("--curves", action="store_true",
                   help="query the sweeps' learning curves (view `curves`: one row per cell and step) instead of `cells`")
    p.set_defaults(func=cmd_query)
