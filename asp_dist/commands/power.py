"""`asp-dist power` (how many trials a comparison needs) and `asp-dist select` (the reproduction study's
selection and power rules on a calibration sweep): both resample a sweep's trials."""

from __future__ import annotations

import argparse
import re

from asp_dist.commands.common import (
    RESAMPLES,
    SEED,
    add_results,
    float_between,
    int_between,
    non_empty,
    non_empty_argument,
)
from asp_dist.errors import SpecError


def _paired_range(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", text)
    if m is None:
        raise SpecError(f"--paired must be N or LO-HI (e.g. 2-4), got {text!r}")
    lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
    if hi < lo:
        raise SpecError(f"--paired {text}: the range ends before it starts")
    return lo, hi


def cmd_power(args: argparse.Namespace) -> int:
    from asp_dist.analysis import power
    from asp_dist.results.query import load_rows

    paired = _paired_range(args.paired)
    rows = load_rows(args.sweeps, results=args.results)
    treatments = [t for t in args.treatments.split(",") if t] if args.treatments else None
    comp = power.comparison(rows, args.domain, args.a, args.b, paired=paired, condition=args.condition,
                            treatments=treatments, metric=args.metric)
    est = power.estimate(comp, args.test, alpha=args.alpha, target=args.target, resamples=args.resamples,
                         seed=args.seed)
    print(power.report(est, fresh_from=args.fresh_from))
    return 0


def cmd_select(args: argparse.Namespace) -> int:
    from asp_dist.analysis.calibration import report
    from asp_dist.core.registry import DOMAINS
    from asp_dist.results.query import load_rows

    if args.domain not in DOMAINS:
        raise SpecError(f"unknown domain {args.domain!r}; choose one of {', '.join(DOMAINS)}")
    rows = load_rows(args.sweeps, results=args.results)
    if not (rows["domain"] == args.domain).any():
        raise SpecError(f"no {args.domain} rows in {', '.join(args.sweeps)}")
    try:
        print(report(rows, args.domain, resamples=args.resamples))
    except ValueError as e:
        raise SpecError(str(e)) from None
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("power", help="how many trials a comparison needs: estimated power by trial count, "
                                     "from a sweep's rows (resampling its trials)",
                       description="Power of the paper's test (Friedman + Nemenyi) or Wilcoxon-Holm for 'A better "
                                   "than B' over a paired range, at the sweep's trial count and at larger ones, by "
                                   "resampling whole trials; the trial count for --target and the trial range to "
                                   "add (asp_dist/analysis/power.py).")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP", type=non_empty_argument)
    p.add_argument("--domain", required=True)
    p.add_argument("--a", required=True, metavar="TREATMENT", help="the treatment expected better, e.g. asp")
    p.add_argument("--b", required=True, metavar="TREATMENT", help="the one it is compared with, e.g. osp")
    p.add_argument("--treatments", type=non_empty, default=None, metavar="T1,T2,...",
                   help="the treatments the test ranks (default: every one in range, as the stats job)")
    p.add_argument("--paired", default=None, metavar="LO-HI", help="paired range (default: all in the rows)")
    p.add_argument("--condition", default=None, help="the condition, as the report names it (e.g. vae_latent_dim=8)")
    p.add_argument("--test", default="friedman-nemenyi", choices=("friedman-nemenyi", "wilcoxon-holm"))
    p.add_argument("--metric", default="eval_mixed")
    p.add_argument("--alpha", type=float_between(0, 1), default=0.05)
    p.add_argument("--target", type=float_between(0, 1), default=0.8, help="the power to reach (default 0.8)")
    p.add_argument("--resamples", type=RESAMPLES, default=1000, help="resamples per trial count (default 1000)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--fresh-from", type=int_between(0, 2**63 - 1, "trial ids are 64-bit"), default=None,
                   metavar="TRIAL",
                   help="also print the trial range of a replication on fresh trials from this id (e.g. 2000)")
    add_results(p)
    p.set_defaults(func=cmd_power)

    p = sub.add_parser("select", help="the reproduction study's selection and power rules on a calibration sweep "
                                      "(docs/reproduction.md)")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP", type=non_empty_argument)
    p.add_argument("--domain", required=True, help="particles | vae | levers | signaling")
    p.add_argument("--resamples", type=RESAMPLES, default=5000, help="bootstrap resamples of the power estimate")
    add_results(p)
    p.set_defaults(func=cmd_select)
