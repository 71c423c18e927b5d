"""`asp-dist tune`: every method of a tune space searched on one budget with a Ray Tune search algorithm
(asp_dist.sweep.tuning); the plan is read and checked before Ray is imported or anything is written."""

from __future__ import annotations

import argparse
import sys

from asp_dist.commands.common import (
    MAX_FAILURES,
    SEED,
    WORKERS,
    add_results,
    check_data,
    int_between,
    non_empty,
    seconds,
)
from asp_dist.errors import SpecError


def cmd_tune(args: argparse.Namespace) -> int:
    import dataclasses
    import signal

    from asp_dist.commands.sweep import check_ray_temp_dir
    from asp_dist.sweep import signals
    from asp_dist.sweep.preflight import check_run_options
    from asp_dist.sweep.tune_plan import SCHEDULERS, SEARCHES, TunePlan, check_scheduler

    check_run_options(args.workers, args.max_failures, args.checkpoint_every)
    check_ray_temp_dir(args.ray_temp_dir)
    if args.search is not None and args.search not in SEARCHES:
        raise SpecError(f"--search must be one of {', '.join(SEARCHES)}, got {args.search!r}")
    if args.scheduler is not None and args.scheduler not in SCHEDULERS:
        raise SpecError(f"--scheduler must be one of {', '.join(SCHEDULERS)}, got {args.scheduler!r}")
    plan = TunePlan.from_space(args.space, args.name)
    overrides = {k: v for k, v in (("budget", args.budget), ("search", args.search), ("seed", args.seed),
                                   ("scheduler", args.scheduler)) if v is not None}
    if overrides:
        plan.settings = dataclasses.replace(plan.settings, **overrides)
        if "scheduler" in overrides:  # the space's grace_points against its cells, as the plan checks its own
            check_scheduler(plan.settings, [c for s in plan.searches.values() for c in s.cells], "--scheduler")
    check_data([c for s in plan.searches.values() for c in s.cells])
    with signals.sigterm_as_interrupt():
        try:
            from asp_dist.sweep.tune_run import run_tune

            result = run_tune(plan, results=args.results, workers=args.workers, ray_temp_dir=args.ray_temp_dir,
                              checkpoint_every_s=args.checkpoint_every, max_failures=args.max_failures)
        except KeyboardInterrupt:
            signum = signals.interrupted_by or signal.SIGINT
            print(f"asp-dist: interrupted ({signal.Signals(signum).name}); finished cells and configurations are "
                  f"kept: run the same command again to continue", file=sys.stderr)
            return 128 + signum
    return 0 if len(result.best) == len(plan.searches) else 1


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tune", help="tune every method of a tune space on the same budget (Ray Tune search)",
                       description="Search each method's knobs ([tune] of the space: budget, search, seed, metric, "
                                   "scheduler, ranges) on the space's calibration cells, the same number of "
                                   "configurations for every method; then train each method's default and its top_k "
                                   "best on the validation trials and choose there (top_k = 0: the search's best). "
                                   "Resumable: run the same command again after a stop. Writes the cells' rows, "
                                   "configurations.parquet (both stages) and tuned.toml under DIR/NAME.")
    p.add_argument("space", help="a tune space: tune_spaces/<name>.toml or a path")
    p.add_argument("--name", type=non_empty, help="the tune run's name (default: the space's)")
    add_results(p)
    p.add_argument("--workers", type=WORKERS, default=2, help="configurations trained at once, 1 CPU each (default 2)")
    # every configuration trains all the space's calibration cells: 10^5 per method is already far past a budget
    p.add_argument("--budget", type=int_between(1, 100_000), help="configurations per method (default: the space's "
                                                                   "[tune] budget)")
    p.add_argument("--search", help="tpe | random (default: the space's)")
    p.add_argument("--seed", type=SEED, help="the searcher's seed (default: the space's)")
    p.add_argument("--scheduler", help="none | asha: stop hopeless configurations early on their learning curves, "
                                       "with the space's ASHA settings (default: the space's)")
    p.add_argument("--ray-temp-dir", type=non_empty, metavar="DIR", help="the embedded Ray's temp dir")
    p.add_argument("--max-failures", type=MAX_FAILURES, default=2,
                   help="retries of a crashed configuration (default 2)")
    p.add_argument("--checkpoint-every", type=seconds(), default=30.0, metavar="S",
                   help="seconds between a configuration's checkpoints (default 30)")
    p.set_defaults(func=cmd_tune)
