"""A knob: one field of a cell that a domain declares, with everything the core needs to know about it.

A domain lists its knobs (``Domain.knobs``); `asp_dist.spec` makes each one a field of CellSpec and of
the result row, `asp-dist fields` documents it, spaces and ``--set`` coerce text into its type, and
resolution fills it with its default and checks its choices and bound. Nothing else in the core names
a domain's knob.

Names are the result row's columns, so a domain's knobs carry the domain's name as a prefix
(``vae_latent_dim``): one flat row schema serves every domain without two domains' knobs colliding
(the registry refuses a knob outside its domain's prefix).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

KNOB_TYPES = (int, float, str, bool)


class _Unset:
    def __repr__(self) -> str:
        return "UNSET"


UNSET: Any = _Unset()  # "no neutral value": the knob is part of every cell id it is set in


RANGE_KINDS = ("log_uniform", "uniform", "int", "choice")
METHOD_FLAGS = ("self_play", "paired", "adversarial")  # asp_dist.method_registry.Method's terms


@dataclass(frozen=True)
class Range:
    """Where `asp-dist tune` may look for a knob's value: log-uniform or uniform between low and high, an
    integer in [low, high], or one of `values`. `needs`: the terms a method must train on for the knob to
    matter to it (Method's flags: an adversary's knobs are tuned for ASP only), empty for every method."""

    kind: str
    low: Any = None
    high: Any = None
    values: tuple = ()
    needs: tuple[str, ...] = ()

    def problems(self, name: str, knob_type: type) -> list[str]:
        """What is wrong with this range for a knob `name` of `knob_type` (empty when nothing)."""
        if self.kind not in RANGE_KINDS:
            return [f"{name}: range kind {self.kind!r}; use one of {', '.join(RANGE_KINDS)}"]
        out = [f"{name}: needs {n!r} is no method term ({', '.join(METHOD_FLAGS)})" for n in self.needs
               if n not in METHOD_FLAGS]
        if self.kind == "choice":
            if not self.values:
                out.append(f"{name}: an empty choice")
            elif any(not _is_type(v, knob_type) for v in self.values):
                out.append(f"{name}: choices {list(self.values)} are not all {knob_type.__name__}")
            return out
        numeric = (int,) if self.kind == "int" else (int, float)
        if knob_type is bool or knob_type is str or (self.kind == "int" and knob_type is not int):
            return out + [f"{name}: a {self.kind.replace('_', '-')} range is for a "
                          f"{'integer' if self.kind == 'int' else 'number'} knob, not a {knob_type.__name__} one"]
        if not all(isinstance(v, numeric) and not isinstance(v, bool) and math.isfinite(v) for v in (self.low, self.high)):
            return out + [f"{name}: a {self.kind.replace('_', '-')} range needs two finite "
                          f"{'integers' if self.kind == 'int' else 'numbers'}, got [{self.low!r}, {self.high!r}]"]
        if not self.low < self.high:
            out.append(f"{name}: an empty range [{self.low}, {self.high}] (low must be below high)")
        if self.kind == "log_uniform" and self.low <= 0:
            out.append(f"{name}: a log-uniform range must be above 0, got low = {self.low}")
        if self.low < 0:
            out.append(f"{name}: a range below 0 ({self.low}); knobs are >= 0")
        return out

    def contains(self, value: Any) -> bool:
        if self.kind == "choice":
            return value in self.values
        return self.low <= value <= self.high

    def within(self, outer: Range) -> bool:
        """Every value of this range is one of `outer`'s."""
        if self.kind == "choice":
            return all(outer.contains(v) for v in self.values)
        return outer.kind != "choice" and outer.low <= self.low and self.high <= outer.high

    def describe(self) -> str:
        if self.kind == "choice":
            text = "one of " + " | ".join(str(v) for v in self.values)
        else:
            text = f"{self.kind.replace('_', '-')} [{self.low:g}, {self.high:g}]"
        return text + (f" (methods with {' and '.join(self.needs)})" if self.needs else "")

    def to_toml(self) -> dict[str, Any]:
        return {self.kind: list(self.values) if self.kind == "choice" else [self.low, self.high]}

    @classmethod
    def from_toml(cls, name: str, value: Any, needs: tuple[str, ...] = ()) -> Range:
        """A range as a space file writes it: ``{ log_uniform = [1e-4, 1e-2] }``, ``{ uniform = [a, b] }``,
        ``{ int = [1, 3] }`` or ``{ choice = ["a", "b"] }`` (ValueError naming what is wrong)."""
        if not isinstance(value, dict) or len(value) != 1 or next(iter(value)) not in RANGE_KINDS:
            raise ValueError(f"{name}: write a range as one of "
                             + ", ".join(f"{{ {k} = [...] }}" for k in RANGE_KINDS) + f", got {value!r}")
        (kind, items), = value.items()
        if not isinstance(items, list):
            raise ValueError(f"{name}: {kind} takes a list, got {items!r}")
        if kind == "choice":
            return cls("choice", values=tuple(items), needs=needs)
        if len(items) != 2:
            raise ValueError(f"{name}: {kind} takes [low, high], got {items!r}")
        return cls(kind, items[0], items[1], needs=needs)


def _is_type(value: Any, knob_type: type) -> bool:
    if knob_type is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if knob_type is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, knob_type)


def log_uniform(low: float, high: float, *, needs: tuple[str, ...] = ()) -> Range:
    return Range("log_uniform", low, high, needs=needs)


def uniform(low: float, high: float, *, needs: tuple[str, ...] = ()) -> Range:
    return Range("uniform", low, high, needs=needs)


def integers(low: int, high: int, *, needs: tuple[str, ...] = ()) -> Range:
    return Range("int", low, high, needs=needs)


def choice(*values: Any, needs: tuple[str, ...] = ()) -> Range:
    return Range("choice", values=tuple(values), needs=needs)


@dataclass(frozen=True)
class Knob:
    """One domain knob.

    name      the field and column name, ``<domain>_<knob>``
    type      int, float, str or bool
    default   the domain's value for it: what a spec that leaves it unset runs with
    doc       one line for `asp-dist fields`
    choices   the allowed values of a text knob (empty: any)
    neutral   the value that reproduces the behaviour from before the knob existed: at that value the
              knob is left out of cell ids, seeds and base keys, so adding a knob moves no existing cell
    shapes_base  False for a knob that only changes how the new agents train: cells differing in it
              share one base model
    bound     upper bound of a size-like knob (memory and time), checked when a spec is resolved
    optional  True (the usual): the field is None until resolution fills it from `default`. False: the
              field itself holds `default` (a knob added after rows were recorded, whose unset value is
              stored as such)
    search    where `asp-dist tune` may look for its value (Range), or None: not tuned unless a tune space
              declares a range for it. Only a knob that does not shape the base can have one (every
              configuration of a tune run adopts the same base)
    """

    name: str
    type: type
    default: Any
    doc: str
    choices: tuple[str, ...] = ()
    neutral: Any = UNSET
    shapes_base: bool = True
    bound: int | None = None
    optional: bool = True
    search: Range | None = None

    def problems(self, domain: str) -> list[str]:
        """What is wrong with this declaration for `domain` (empty when nothing)."""
        out = []
        if not isinstance(self.name, str) or not self.name.startswith(f"{domain}_") or self.name == f"{domain}_":
            out.append(f"knob {self.name!r} must be named {domain}_<knob>")
        if self.type not in KNOB_TYPES:
            out.append(f"knob {self.name!r} has type {self.type!r}; use int, float, str or bool")
        if self.choices and (self.type is not str or self.default not in self.choices):
            out.append(f"knob {self.name!r}: choices are for text knobs and must hold the default {self.default!r}")
        if not self.optional and self.default is None:
            out.append(f"knob {self.name!r} is not optional, so it needs a default")
        if not isinstance(self.doc, str) or not self.doc.strip():
            out.append(f"knob {self.name!r} needs a one-line doc")
        if self.search is not None:
            if self.shapes_base:
                out.append(f"knob {self.name!r} shapes the base, so it cannot have a tuning range (every "
                           f"configuration of a tune run adopts the same base)")
            out += [f"knob {p}" for p in self.search.problems(repr(self.name), self.type)]
        return out


# ---- what a fast trainer implements ------------------------------------------------------------------
# A trainer that re-derives a domain's update (a packed trainer) declares, for every knob of its domain,
# which values it implements: `implements = {knob name: ANY | BASE_ONLY | (value, ...)}`. The trainer
# registry (asp_dist.training.engines) refuses a trainer whose declaration misses a knob, so a knob added
# to a domain's game but not to its fast trainer cannot be silently ignored; a cell whose value a trainer
# does not implement trains on the next trainer that does (the reference one implements every value).


class _Marker:
    def __init__(self, name: str):
        self.name = name

    def __repr__(self) -> str:
        return self.name


ANY: Any = _Marker("ANY")  # every value the knob accepts
BASE_ONLY: Any = _Marker("BASE_ONLY")  # a knob of the base's training only: the new agents' update never reads it


def implements_problems(implements: Any, domain_knobs: tuple[Knob, ...] | list[Knob], fields: set[str]) -> list[str]:
    """What is wrong with a trainer's `implements` declaration: a knob of its domain it does not cover, a
    name that is no field (`fields`: every field of a cell), an entry that is neither a marker nor a
    non-empty tuple of values, or a choice the knob does not have."""
    if not isinstance(implements, dict):
        return [f"`implements` is a {type(implements).__name__}, not a dict of knob name -> values"]
    out = []
    missing = [k.name for k in domain_knobs if k.name not in implements]
    if missing:
        out.append(f"it does not say which values it implements of {', '.join(missing)}")
    for name, allowed in implements.items():
        if name not in fields:
            out.append(f"it declares {name!r}, which is no knob")
        elif allowed is not ANY and allowed is not BASE_ONLY and not (isinstance(allowed, tuple) and allowed):
            out.append(f"{name!r} must map to ANY, BASE_ONLY or a non-empty tuple of values, not {allowed!r}")
    by_name = {k.name: k for k in domain_knobs}
    for name, allowed in implements.items():
        knob = by_name.get(name)
        if knob is not None and knob.choices and isinstance(allowed, tuple):
            odd = [v for v in allowed if v not in knob.choices]
            if odd:
                out.append(f"{name!r}: {odd} are not among its choices {knob.choices}")
    return out


def unimplemented(implements: dict[str, Any], spec: Any) -> list[str]:
    """`knob=value` for each value of (resolved) `spec` that `implements` does not cover."""
    return [f"{name}={getattr(spec, name)!r}" for name, allowed in implements.items()
            if isinstance(allowed, tuple) and getattr(spec, name) not in allowed]
