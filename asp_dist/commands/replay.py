"""`asp-dist replay`: train one finished cell again here and say which columns of its row differ."""

from __future__ import annotations

import argparse

from asp_dist.commands.common import add_results, non_empty_argument


def cmd_replay(args: argparse.Namespace) -> int:
    """Exit 0 when the replayed row equals the stored one, 1 when a column differs; a bad input is exit 2."""
    from asp_dist.results.store import locate_sweep
    from asp_dist.sweep.replay import replay_cell

    result = replay_cell(locate_sweep(args.sweep, args.results), args.cell_id)
    print(result.text())
    return 0 if result.identical else 1


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="train one finished cell again and compare its row (exit 0 same, 1 not)",
                       description="Train one finished cell of a sweep again from its stored spec, on this machine "
                                   "(alone, or with its pack when it was trained in one; its stored base when the "
                                   "sweep has it), and report which non-volatile columns of its row differ and what "
                                   "differs in the row's provenance. Writes nothing. Exit 0 identical, 1 a column "
                                   "differs, 2 bad input.")
    p.add_argument("sweep", metavar="SWEEP", type=non_empty_argument, help="sweep name (under --results) or directory")
    p.add_argument("cell_id", metavar="CELL_ID", type=non_empty_argument,
                   help="the cell (`asp-dist query SWEEP --columns cell_id` lists them)")
    add_results(p)
    p.set_defaults(func=cmd_replay)
