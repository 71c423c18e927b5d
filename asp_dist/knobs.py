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

from dataclasses import dataclass
from typing import Any

KNOB_TYPES = (int, float, str, bool)


class _Unset:
    def __repr__(self) -> str:
        return "UNSET"


UNSET: Any = _Unset()  # "no neutral value": the knob is part of every cell id it is set in


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
