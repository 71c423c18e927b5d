"""What several commands share: --set KEY=VALUE, --results DIR, the data check before any work, and the
argparse `type=` helpers that declare each numeric or path flag's bounds beside the flag itself."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
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


def refuse_set(items: Sequence[str], taken: dict[str, str]) -> None:
    """--set of a field the command sets otherwise (its own flag, its positional NAME, its own choice): one line
    naming the --set and what to do instead, not a TypeError for a keyword given twice."""
    for item in items:
        key = item.partition("=")[0].strip()
        if key in taken:
            raise SpecError(f"--set {item!r}: {taken[key]}")


def check_data(specs: Sequence[CellSpec]) -> None:
    """Each domain of the cells loads and verifies the data its cells read (Domain.check_data), so a missing
    or corrupt copy is refused before any work starts (e.g. MNISTError; `main` prints it as one line)."""
    from asp_dist.core.registry import get_domain

    by_domain: dict[str, list[CellSpec]] = {}
    for spec in specs:
        by_domain.setdefault(spec.domain, []).append(spec)
    for name, of_domain in sorted(by_domain.items()):
        get_domain(name).check_data(of_domain)


# ---- argparse types: a bad value is argparse's one line, exit 2, before the command runs --------------------
# cli.Parser.error words "argument --x: must be ..." as "--x must be ...", the form of the commands' own checks.

# Bootstrap and power resamples: 10^5 leave a Monte-Carlo error far below the interval's own width at any trial
# count a sweep has, and keep the index arrays (resamples x rows) within memory; a huge count ran out of it.
MAX_RESAMPLES = 100_000
# numpy's RandomState (Optuna's TPE, Tune's random search) takes seeds below 2^32, and `tune` adds 1009 per method.
MAX_SEED = 2**31 - 1
# Timeouts and intervals: past about 3e10 s threading's and socket's waits overflow time_t; a day is plenty.
MAX_SECONDS = 86_400.0


def int_between(lo: int, hi: int | None = None, why: str = "") -> Callable[[str], int]:
    """An integer flag in [lo, hi] (no upper bound: hi None); `why` follows the upper bound's refusal."""

    def parse(text: str) -> int:
        value = int(text)  # ValueError: argparse says "invalid int value: 'x'"
        if value < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {value}")
        if hi is not None and value > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi}, got {value}{f' ({why})' if why else ''}")
        return value

    parse.__name__ = "int"
    return parse


def float_between(lo: float, hi: float | None = None, *, unit: str = "") -> Callable[[str], float]:
    """A finite float flag above lo (excluded) and, when hi is given, below hi (excluded)."""

    def parse(text: str) -> float:
        value = float(text)  # ValueError: argparse says "invalid float value: 'x'"
        ok = math.isfinite(value) and lo < value and (hi is None or value < hi)
        if hi is None and not ok:
            raise argparse.ArgumentTypeError(f"must be > {lo:g}{unit} and finite, got {text}")
        if not ok:
            raise argparse.ArgumentTypeError(f"must be between {lo:g} and {hi:g}{unit} (both excluded), got {text}")
        return value

    parse.__name__ = "float"
    return parse


def seconds(hi: float = MAX_SECONDS) -> Callable[[str], float]:
    """A duration flag: more than 0 and at most `hi` seconds."""
    positive = float_between(0, unit=" seconds")

    def parse(text: str) -> float:
        value = positive(text)
        if value > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi:g} seconds, got {text}")
        return value

    parse.__name__ = "float"
    return parse


def non_empty(text: str) -> str:
    """A path, name or URI flag: "" (or blanks) would silently mean the current directory or the default."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty; give a value or leave the flag out")
    return text


def non_empty_argument(text: str) -> str:
    """A positional SWEEP, path or id: "" would be the current directory."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty; give a value")
    return text


RESAMPLES = int_between(100, MAX_RESAMPLES, "more do not narrow the interval measurably")
SEED = int_between(0, MAX_SEED)
# Ray runs one cell per worker: 10^4 at once is beyond any cluster here, and a huge count would start them all.
WORKERS = int_between(1, 10_000)
# A cell whose worker died 100 times in a row will die again: more retries only hide it.
MAX_FAILURES = int_between(0, 100)


def add_results(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results", default=store.DEFAULT_RESULTS, metavar="DIR", type=non_empty,
                   help=f"results root; sweep NAME lives in DIR/NAME (default: {store.DEFAULT_RESULTS})")
