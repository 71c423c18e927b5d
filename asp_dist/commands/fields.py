"""`asp-dist fields`: every cell field (the common knobs and each domain's) with its default and meaning, and
the range `asp-dist tune` searches where the knob declares one."""

from __future__ import annotations

import argparse
import sys

from asp_dist.spec import FIELD_DOCS, FIELD_NAMES, SEARCH, CellSpec


def cmd_fields(args: argparse.Namespace) -> int:
    from asp_dist.domains import DOMAINS, get_domain
    from asp_dist.domains.registry import set_aside
    from asp_dist.method_registry import METHODS
    from asp_dist.spec import COMMON_DEFAULTS

    for problem in [*set_aside().values(), *METHODS.problems().values()]:  # named; the others are listed
        print(f"asp-dist: warning: {problem}", file=sys.stderr)
    chosen = [get_domain(args.domain)] if args.domain is not None else [DOMAINS[name] for name in DOMAINS]
    own = {k.name for domain in DOMAINS.values() for k in domain.knobs}
    shown = {k.name for domain in chosen for k in domain.knobs}
    defaults = {**COMMON_DEFAULTS, **(chosen[0].defaults if args.domain is not None else {}),
                **{k: v for domain in chosen for k, v in domain.knob_defaults.items()}}
    for name in FIELD_NAMES:
        if name in own and name not in shown:  # another domain's knob
            continue
        value = defaults.get(name, getattr(CellSpec(), name))
        tuned = f" [tune: {SEARCH[name].describe()}]" if name in SEARCH else ""
        print(f"{name:26s} {value!s:>10s}  {FIELD_DOCS[name]}{tuned}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fields", help="list every cell field with its default and meaning")
    p.add_argument("--domain", help="show this domain's defaults and knobs only")
    p.set_defaults(func=cmd_fields)
