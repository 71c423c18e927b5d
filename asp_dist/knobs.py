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
