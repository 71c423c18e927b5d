"""`asp-dist fields`: every cell field (the common knobs and each domain's) with its default and meaning, and
the range `asp-dist tune` searches where the knob declares one."""

from __future__ import annotations

import argparse
import sys

from asp_dist.spec import FIELD_DOCS, FIELD_NAMES, SEARCH, CellSpec

KNOBS_PAGE = "docs/knobs.md"  # `asp-dist fields --markdown` writes it; tests/test_knobs.py keeps it current


def cmd_fields(args: argparse.Namespace) -> int:
    if args.markdown:
        print(knobs_page(), end="")
        return 0
    from asp_dist.core.registry import DOMAINS, get_domain, set_aside
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


def knobs_page() -> str:
    """docs/knobs.md: every knob of the built-in domains, from the declarations themselves (the common knobs'
    fields in asp_dist/spec.py, each domain's Knob and `defaults`): type, default, allowed values or bound,
    the range `asp-dist tune` searches, and the meaning. Plugins are left out: the page is the same on every
    install."""
    import typing

    from asp_dist.core.registry import DOMAINS
    from asp_dist.spec import CHOICES, COMMON_DEFAULTS, UPPER_BOUNDS

    built_in = [d for d in DOMAINS.values() if type(d).__module__.startswith("asp_dist.")]
    own = {k.name for d in DOMAINS.values() for k in d.knobs}
    hints = typing.get_type_hints(CellSpec)

    def text(words: str) -> str:  # a table cell: its pipes escaped
        return words.replace("|", "\\|")

    def cell(value) -> str:
        return "unset" if value is None else text(f"`{value}`")

    def allowed(name: str, bound: int | None) -> str:
        if name in CHOICES:
            return " \\| ".join(f"`{c}`" for c in CHOICES[name])
        return f"≤ {bound:,}" if bound is not None else ""

    def type_name(name: str) -> str:
        hint = hints.get(name)
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return (args[0] if args else hint).__name__

    lines = ["# Knobs", "",
             "Every field of a cell, as declared in code: the common knobs (`asp_dist/spec.py`) and each built-in",
             "domain's own (`Knob` on its card, `asp_dist/domains/<name>/__init__.py`). *Default* is what a spec that",
             "leaves the knob unset runs with; *tune* is the range `asp-dist tune` searches unless a tune space",
             "narrows it (docs/decisions/0052-equal-budget-tuning.md). `asp-dist fields` prints the same for the",
             "installed domains, plugins included.", "",
             f"Generated: `asp-dist fields --markdown > {KNOBS_PAGE}` (tests/test_knobs.py fails when it is stale).", "",
             "## Common knobs", "",
             "Every domain has these; `—` means the domain gives the value (next table).", "",
             "| knob | type | default | allowed | tune | meaning |", "|---|---|---|---|---|---|"]
    for name in FIELD_NAMES:
        if name in own:
            continue
        default = COMMON_DEFAULTS.get(name, getattr(CellSpec(), name))
        default = "—" if default is None and any(name in d.defaults for d in built_in) else cell(default)
        tune = text(SEARCH[name].describe()) if name in SEARCH else ""
        lines.append(f"| `{name}` | {type_name(name)} | {default} | {allowed(name, UPPER_BOUNDS.get(name))} | "
                     f"{tune} | {text(FIELD_DOCS[name])} |")
    given = sorted({k for d in built_in for k in d.defaults})
    lines += ["", "## Each domain's values of the common knobs", "",
              "| knob | " + " | ".join(d.name for d in built_in) + " |", "|---|" + "---|" * len(built_in)]
    for name in [n for n in FIELD_NAMES if n in given]:
        lines.append(f"| `{name}` | " + " | ".join(cell(d.defaults[name]) if name in d.defaults else ""
                                                   for d in built_in) + " |")
    for d in built_in:
        lines += ["", f"## {d.name}", "", "| knob | type | default | allowed | tune | shapes the base | meaning |",
                  "|---|---|---|---|---|---|---|"]
        for k in d.knobs:
            choices = " \\| ".join(f"`{c}`" for c in k.choices) if k.choices else allowed(k.name, k.bound)
            tune = text(k.search.describe()) if k.search is not None else ""
            lines.append(f"| `{k.name}` | {k.type.__name__} | {cell(k.default)} | {choices} | {tune} | "
                         f"{'yes' if k.shapes_base else 'no'} | {text(k.doc)} |")
    return "\n".join(lines) + "\n"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fields", help="list every cell field with its default and meaning")
    p.add_argument("--domain", help="show this domain's defaults and knobs only")
    p.add_argument("--markdown", action="store_true",
                   help=f"print {KNOBS_PAGE}: every built-in domain's knobs as Markdown tables")
    p.set_defaults(func=cmd_fields)
