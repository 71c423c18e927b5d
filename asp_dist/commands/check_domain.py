"""`asp-dist check-domain`: the domain contract checker and one tiny cell of each method, on a domain's smoke spec."""

from __future__ import annotations

import argparse
import sys

from asp_dist.commands.common import parse_overrides, refuse_set
from asp_dist.errors import SpecError
from asp_dist.spec import CellSpec


def cmd_check_domain(args: argparse.Namespace) -> int:
    """The contract checker as a command: what a plugin author runs before anything else."""
    from asp_dist.core.contract import ContractError, check_domain
    from asp_dist.core.registry import get_domain
    from asp_dist.method_registry import method_order
    from asp_dist.training.cell import run_cell

    # The checker sets these itself: the domain is NAME, and it runs every method at two paired counts.
    refuse_set(args.set, {"domain": "the domain is check-domain's NAME argument; give it there",
                          "method": "check-domain runs every method itself; leave method out",
                          "paired": "check-domain chooses the paired counts itself (4, then 2); leave paired out"})
    domain = get_domain(args.name)  # a plugin that did not load: its one line
    spec = CellSpec(domain=args.name, method="asp", paired=4, **{**domain.smoke, **parse_overrides(args.set)})
    spec.resolved()  # a bad knob value: SpecError, one line
    steps = [("contract (same seed -> same base, P, U, losses, outputs, metrics; shapes; gradients)",
              lambda: check_domain(domain, spec)),
             ("trainers (each fast trainer says which values of every knob it implements)",
              lambda: check_trainers(args.name))]
    steps += [(f"one {method} cell", lambda method=method: run_cell(spec.replace(method=method, paired=2)))
              for method in method_order()]
    for what, step in steps:
        try:
            done = step()
            summary = f": {cell_summary(done, domain)}" if isinstance(done, dict) else ""
        except ContractError as err:
            print(f"asp-dist: error: domain {args.name!r} breaks the contract: {err}", file=sys.stderr)
            return 1
        except SpecError:
            raise
        except Exception as err:  # the plugin's own code failed: name where, in one line
            print(f"asp-dist: error: domain {args.name!r}: {what} failed: {type(err).__name__}: {err}",
                  file=sys.stderr)
            return 1
        print(f"ok  {what}{summary}")
    print(f"domain {args.name}: passes the contract (smoke spec: {', '.join(f'{k}={v}' for k, v in domain.smoke.items()) or 'defaults'})")
    return 0


def cell_summary(row: dict, domain) -> str:
    """The base's score against its bar and the domain's metrics, from a cell's row."""
    def number(value) -> str:
        return f"{value:.4g}" if isinstance(value, (int, float)) else str(value)

    bar = f" (bar {number(row[domain.accept_field])})" if domain.accept_field in row else ""
    metrics = ", ".join(f"{m} {number(row[f'eval_{m}'])}" for m in domain.metrics if f"eval_{m}" in row)
    return f"base score {number(row.get('base_score'))}{bar}; {metrics}"


def check_trainers(name: str) -> None:
    """ContractError naming a trainer of the domain that the trainer registry refuses (asp_dist.training.engines:
    its `implements` leaves a knob of the domain out)."""
    from asp_dist.core.contract import ContractError
    from asp_dist.core.registry import get_domain
    from asp_dist.training.engines import trainer_problems

    for trainer in get_domain(name).trainers:
        problems = trainer_problems(trainer, name)
        if problems:
            raise ContractError(f"trainer {trainer.__name__} is refused: {'; '.join(problems)}")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check-domain", help="run the domain contract checker on a registered domain (a plugin's)",
                       description="Check a domain as a plugin author would: same seed gives the same base, "
                                   "paired and unpaired data, losses, outputs and metrics; shapes and gradients "
                                   "are as the contract says; one tiny cell of each method runs. On the domain's "
                                   "smoke spec (Domain.smoke), changed with --set.")
    p.add_argument("name", help="domain name, as registered (asp-dist fields lists them)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="change a knob of the smoke spec")
    p.set_defaults(func=cmd_check_domain)
