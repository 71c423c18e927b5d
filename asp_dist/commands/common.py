"""What several commands share: --set KEY=VALUE, --results DIR, and the data check before any work."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from asp_dist.errors import SpecError
from asp_dist.results import store
from asp_dist.spec import CellSpec, coerce_field


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SpecError(f"--set expects KEY=VALUE, got {item!r}")
        out[key.strip()] = coerce_field(key.strip(), value.strip())
    return out


def check_data(specs: Sequence[CellSpec]) -> None:
    """Each domain of the cells loads and verifies the data its cells read (Domain.check_data), so a missing
    or corrupt copy is refused before any work starts (e.g. MNISTError; `main` prints it as one line)."""
    from asp_dist.domains import get_domain

    by_domain: dict[str, list[CellSpec]] = {}
    for spec in specs:
        by_domain.setdefault(spec.domain, []).append(spec)
    for name, of_domain in sorted(by_domain.items()):
        get_domain(name).check_data(of_domain)


def add_results(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results", default=store.DEFAULT_RESULTS, metavar="DIR",
                   help=f"results root; sweep NAME lives in DIR/NAME (default: {store.DEFAULT_RESULTS})")
