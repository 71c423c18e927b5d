"""`asp-dist compare`: are two runs of the same grid equivalent (medians, bootstrap intervals, a margin)?"""

from __future__ import annotations

import argparse

from asp_dist.commands.common import RESAMPLES, SEED, add_results, non_empty_argument


def cmd_compare(args: argparse.Namespace) -> int:
    """Exit 0 when A and B are equivalent, 1 when not; a bad input is a SpecError (exit 2)."""
    from asp_dist.analysis.compare import parse_margin, run_compare

    margin = parse_margin(args.margin) if args.margin is not None else None
    result = run_compare(args.a, args.b, domain=args.domain, metric=args.metric, by=args.by, margin=margin,
                         n_boot=args.bootstrap, seed=args.seed, results=args.results)
    print(result.text(markdown=args.markdown))
    return 0 if result.equivalent else 1


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="are two runs of the same grid equivalent? (exit 0 yes, 1 no)",
                       description="Per group (domain, method, paired, --by columns): each run's median with its "
                                   "bootstrap 95 % interval, whether each lies inside the other's, and the interval "
                                   "of the median per-trial difference A − B (against --margin). Equivalent: every "
                                   "median inside the other's interval, no unmatched group, and with --margin every "
                                   "difference interval inside ±margin. Exit 0 equivalent, 1 not, 2 bad input.")
    p.add_argument("a", metavar="SWEEP_A", type=non_empty_argument,
                   help="sweep name (under --results) or directory, or a .parquet file of rows")
    p.add_argument("b", metavar="SWEEP_B", type=non_empty_argument, help="the same for the other run")
    add_results(p)
    p.add_argument("--by", nargs="+", default=[], metavar="COL",
                   help="extra grouping columns (e.g. vae_latent_dim)")
    p.add_argument("--margin", metavar="M",
                   help="equivalence margin of the per-trial difference: metric units (0.01) or a percentage of "
                        "|B's median| (5%%)")
    p.add_argument("--domain", help="compare this domain's rows only")
    p.add_argument("--metric", default="eval_mixed", help="metric column (default: eval_mixed)")
    p.add_argument("--bootstrap", type=RESAMPLES, default=5000, help="bootstrap resamples (default 5000)")
    p.add_argument("--seed", type=SEED, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--markdown", action="store_true", help="the table as GitHub Markdown")
    p.set_defaults(func=cmd_compare)
