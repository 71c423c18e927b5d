"""`asp-dist decide`: a sweep grown stage by stage until its registered comparisons are decided
(asp_dist.study.decide_run); the registration and the flags are checked before Ray is imported."""

from __future__ import annotations

import argparse

from asp_dist.commands.common import int_between


def cmd_decide(args: argparse.Namespace) -> int:
    from asp_dist.commands.common import check_data
    from asp_dist.commands.sweep import _interruptible, _run_options, check_run_flags, tracking_settings
    from asp_dist.study.decide_plan import DecidePlan
    from asp_dist.study.decide_run import DECIDE_FILE, check_record, read_record
    from asp_dist.sweep.ledger import sweep_dir_for

    name: list[str] = []

    def run() -> int:
        check_run_flags(args)
        plan = DecidePlan.from_space(args.space, args.name)
        name.append(plan.name)
        check_record(plan, read_record(sweep_dir_for(args.results, plan.name)))  # a changed registration: one line
        check_data(plan.specs)
        tracking = tracking_settings(args, plan.name, plan.logging)
        if args.address is not None:
            from asp_dist.sweep.preflight import check_address

            check_address(args.address, args.connect_timeout)
        from asp_dist.study.decide_run import run_decide

        result = run_decide(plan, _run_options(args, tracking), stop_after=args.stages)
        if not result.complete:
            return 1
        print(f"  the looks: {result.sweep_dir / DECIDE_FILE}; the report: asp-dist stats {result.sweep_dir}")
        return 0

    again = "run the same asp-dist decide command again to continue"
    return _interruptible(args, lambda: name[0] if name else None, run, again)


def add_parser(sub: argparse._SubParsersAction) -> None:
    from asp_dist.commands.sweep import _add_run_options

    p = sub.add_parser("decide", help="grow a sweep in stages until its registered comparisons are decided",
                       description="Run the space's grid a stage of trials at a time ([decide] of the space: the "
                                   "comparisons, test, alpha, stage size; the grid's trials are the most it may "
                                   "use), test after each stage, and stop when every comparison is decided. "
                                   "Resumable: run the same command again after a stop. Writes the rows like a "
                                   "sweep and the looks to NAME/decide.json.")
    p.add_argument("space", help="a decide space: tune_spaces/<name>.toml or a path")
    p.add_argument("--name", default=None, help="sweep name (default: the space's name)")
    p.add_argument("--stages", type=int_between(1), default=None, metavar="N",
                   help="run at most N more stages, then stop (default: until decided); the next run continues")
    _add_run_options(p)
    p.set_defaults(func=cmd_decide)
