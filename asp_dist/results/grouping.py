"""Conditions and treatments: the one rule for how a domain's cells are grouped. The analysis uses it on
result rows (asp_dist.analysis.layout) and the trackers on the plan's specs (asp_dist.tracking.cells), so
a tracker's run path names the condition and treatment the report shows.

- *knob*: a CellSpec field outside NOT_KNOBS (the identity, and switches that change no result).
- *shared knob*: varied within every method of the domain, companion arms (``osp@default``) aside: a
  companion may run at fewer settings than its method. Its values make the *condition*
  (``vae_latent_dim=8``, several joined by ", "), or "all" when the domain has no shared knob.
- *method knob*: varied within some methods only. It splits a method into *treatments*
  (``asp[lambda_unpaired=0.5]``).

Plain Python, no pandas or torch: the trackers name runs without pandas. The module sits at the results
stage because tracking lies below analysis in the import flow (tests/test_architecture.py), and this is
the lowest stage both reach. Each caller decides which fields are candidate knobs (both: CellSpec field
order) and when two values count as different (`varies`): pandas' nunique on rows, repr on specs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

from asp_dist.method_registry import is_companion

IDENTITY = ("domain", "method", "paired", "trial", "root_seed")
NOT_KNOBS = frozenset(IDENTITY) | {"record_figure_data"}


@dataclass(frozen=True)
class Grouping:
    """Which knobs of one domain make its conditions and which split its methods into treatments."""

    shared: list[str]  # varied within every method, in the caller's knob order
    method_only: dict[str, list[str]]  # every method (in the caller's order) -> knobs varied only within it

    def condition_of(self, values: Mapping[str, Any]) -> str:
        return condition_label(self.shared, values)

    def treatment_of(self, values: Mapping[str, Any]) -> str:
        method = values["method"]
        return treatment_label(method, self.method_only.get(method, []), values)


def split_knobs(methods: Sequence[str], knobs: Sequence[str], varies: Callable[[str, str], bool]) -> Grouping:
    """Sort the candidate `knobs` into shared and method-only ones; `varies(knob, method)` says whether the
    knob takes more than one value among the method's rows. A knob no method varies is neither."""
    shared: list[str] = []
    method_only: dict[str, list[str]] = {m: [] for m in methods}
    main = [m for m in methods if not is_companion(m)] or list(methods)
    for knob in knobs:
        varied_in = [m for m in methods if varies(knob, m)]
        if not varied_in:
            continue
        if all(m in varied_in for m in main):
            shared.append(knob)
        else:
            for m in varied_in:
                method_only[m].append(knob)
    return Grouping(shared, method_only)


def group_records(records: Sequence[Mapping[str, Any]], knobs: Sequence[str],
                  same: Callable[[Any], Any] = repr) -> Grouping:
    """split_knobs over one domain's dicts (specs or rows). Two values of a knob are the same when `same`
    maps them to equal keys (by default their repr). A missing key reads as None."""
    by_method: dict[str, list[Mapping[str, Any]]] = {}
    for r in records:
        by_method.setdefault(r["method"], []).append(r)
    return split_knobs(list(by_method), knobs,
                       lambda knob, m: len({same(r.get(knob)) for r in by_method[m]}) > 1)


def fmt_value(v: Any) -> str:
    """A knob's value in a label: integral floats without ".0" (``2``, not ``2.0``), other floats with :g."""
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def condition_label(shared: Sequence[str], values: Mapping[str, Any]) -> str:
    """``k=v, k2=v2`` over the shared knobs, in their order; "all" when there are none."""
    if not shared:
        return "all"
    return ", ".join(f"{k}={fmt_value(values.get(k))}" for k in shared)


def treatment_label(method: str, knobs: Sequence[str], values: Mapping[str, Any]) -> str:
    """The method, with its method-only knobs in brackets when it has any: ``asp[lambda_unpaired=0.5]``."""
    if not knobs:
        return method
    return method + "[" + ", ".join(f"{k}={fmt_value(values.get(k))}" for k in knobs) + "]"
