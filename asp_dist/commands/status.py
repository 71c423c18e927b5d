"""`asp-dist status`: done / failed / pending cells of a sweep (no Ray, no torch)."""

from __future__ import annotations

import argparse

from asp_dist.commands.common import add_results


def cmd_status(args: argparse.Namespace) -> int:
    from asp_dist.sweep.ledger import sweep_status

    print(sweep_status(args.name, args.results, list_failed=args.failed))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="done / failed / pending cells of a sweep")
    p.add_argument("name")
    p.add_argument("--failed", action="store_true",
                   help="list every failed cell with its error (default: the failures grouped by cause)")
    add_results(p)
    p.set_defaults(func=cmd_status)
